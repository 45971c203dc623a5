"""Benchmark of ``gyrocal replay``: samples/s through the whole engine off line, and reader speeds.

    .venv/bin/python benchmarks/bench_replay.py [--quick] [--json OUT.json]

1. Replay: a 1-hour 2 kHz tumble log (quick: 5 minutes), generated here block by block (a minute
   at a time, so memory stays small) and fed through the replay link into the daemon's Engine
   with the default settings (chunks of 1 s). ``samples_per_s`` counts the engine's time only: the
   time spent generating the synthetic samples is measured apart and left out (``gen_s``).
   The target is 200,000 samples/s (100x real time at 2 kHz).
2. CSV read: ``read_any`` on a CSV log of the same signal (10 minutes at 2 kHz; quick: 1 minute).
3. python-can .blf read: ``read_any`` on a .blf written with python-can's ``can.Logger`` from the
   CAN codec's frames (3 to 4 frames per sample; 2 minutes at 2 kHz, ``--blf-seconds`` for
   longer; quick: 15 s), i.e. our BLF container reader, the bulk DBC decoding and the log
   assembly. ``reference_samples_per_s``: the same file through ``can.LogReader`` and the decoder
   frame by frame (``read_canlog(fast=False)``), which gives the same samples bit for bit.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gyrocal.daemon.config import load_config
from gyrocal.daemon.ring import SAMPLE_DTYPE
from gyrocal.logformat import write_log
from gyrocal.protocol.messages import Hello, Sample
from gyrocal.readers import read_any
from gyrocal.replay.run import Replay
from gyrocal.replay.source import Recording
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import SessionStream, TruthModel

RATE = 2000.0
COLS = ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp")


class SyntheticRecording(Recording):
    """A tumble log generated block by block; ``gen_s`` sums the time spent generating."""

    def __init__(self, seconds: float) -> None:
        super().__init__("synthetic", "csv")
        self.seconds = seconds
        self.gen_s = 0.0
        self.gen_cpu_s = 0.0
        self.first_hello = Hello(7, "1.0.0", 1, int(RATE))

    def events(self) -> Iterator[tuple[str, object]]:
        yield "msg", self.first_hello
        stream = SessionStream(TruthModel(), tumble(1.2, 0.4), RATE, seed=11, boot=1)
        n_total, block, done = int(self.seconds * RATE), int(60 * RATE), 0
        while done < n_total:
            t0, c0 = time.perf_counter(), time.process_time()
            n = min(block, n_total - done)
            cols = stream.chunk(n)
            out = np.zeros(n, dtype=SAMPLE_DTYPE)
            out["seq"] = np.arange(done, done + n)
            for c in COLS:
                out[c] = cols[c]
            self.gen_s += time.perf_counter() - t0
            self.gen_cpu_s += time.process_time() - c0
            for i in range(0, n, 4096):
                yield "samples", out[i:i + 4096]
            done += n

    def dropped(self) -> dict[str, int]:
        return {}


def bench_replay(seconds: float, tmp: Path, chunk_s: float = 1.0) -> dict:
    rec = SyntheticRecording(seconds)
    state = tmp / f"state-{chunk_s}"
    state.mkdir()
    cfg = load_config(None, {"state_dir": str(state), "control_socket": str(tmp / "c.sock"),
                             "watchdog": False})
    r = Replay(rec, cfg, chunk_s=chunk_s)
    c0 = time.process_time()
    r.run()
    cpu_s = time.process_time() - c0 - rec.gen_cpu_s
    s = r.summary()
    engine_s = r.wall_s - rec.gen_s
    return {"log_s": seconds, "rate_hz": RATE, "chunk_s": chunk_s, "samples": s["samples"],
            "wall_s": round(r.wall_s, 2), "gen_s": round(rec.gen_s, 2), "engine_s": round(engine_s, 2),
            "engine_cpu_s": round(cpu_s, 2), "samples_per_s": round(s["samples"] / engine_s),
            "samples_per_cpu_s": round(s["samples"] / cpu_s), "x_real_time": round(seconds / engine_s, 1),
            "pushes": len(s["pushes"]), "decisions": len(s["decisions"])}


def bench_csv(seconds: float, tmp: Path) -> dict:
    cols = SessionStream(TruthModel(), tumble(1.2, 0.4), RATE, seed=12, boot=0).chunk(int(seconds * RATE))
    path = tmp / "log.csv"
    write_log(path, {c: cols[c] for c in COLS})
    t0, c0 = time.perf_counter(), time.process_time()
    log = read_any(path)
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"log_s": seconds, "samples": len(log), "bytes": path.stat().st_size, "seconds": round(dt, 2),
            "samples_per_s": round(len(log) / dt), "samples_per_cpu_s": round(len(log) / cpu)}


def bench_blf(seconds: float, tmp: Path, reference: bool = True) -> dict:
    import can

    from gyrocal.protocol.can_codec import CanCodec
    from gyrocal.readers import ReadOptions
    from gyrocal.readers.canlog import read_canlog

    cols = SessionStream(TruthModel(), tumble(1.2, 0.4), RATE, seed=13, boot=0).chunk(int(seconds * RATE))
    codec = CanCodec()
    path = tmp / "log.blf"
    frames = 0
    with can.Logger(str(path)) as out:
        for f in codec.encode(Hello(7, "1.0.0", 1, int(RATE))):
            out(f)
        for i in range(len(cols["t"])):
            s = Sample(i, float(cols["t"][i]), (cols["wx"][i], cols["wy"][i], cols["wz"][i]),
                       (cols["ax"][i], cols["ay"][i], cols["az"][i]), float(cols["temp"][i]))
            for f in codec.encode(s):
                f.timestamp = float(cols["t"][i])
                out(f)
                frames += 1
    t0, c0 = time.perf_counter(), time.process_time()
    log = read_any(path)
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    out = {"log_s": seconds, "samples": len(log), "frames": frames, "bytes": path.stat().st_size,
           "seconds": round(dt, 3), "samples_per_s": round(len(log) / dt),
           "samples_per_cpu_s": round(len(log) / cpu), "dropped": log.dropped}
    if reference:
        t0 = time.perf_counter()
        ref = read_canlog(str(path), ReadOptions(), fast=False)
        dt = time.perf_counter() - t0
        out["reference_seconds"] = round(dt, 2)
        out["reference_samples_per_s"] = round(len(ref) / dt)
        out["same_as_reference"] = all(np.array_equal(ref[c], log[c]) for c in ref.columns)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short logs (5 min replay, 1 min CSV, 15 s .blf)")
    ap.add_argument("--json", metavar="OUT.json", help="write the figures here ('-' = stdout)")
    ap.add_argument("--blf-seconds", type=float, metavar="S",
                    help="length of the .blf log (default 120; quick: 15); writing it with python-can "
                         "takes about 1 min per 2 min of log")
    ap.add_argument("--blf-only", action="store_true", help="only the .blf read")
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the frame-by-frame can.LogReader reference read of the .blf")
    args = ap.parse_args(argv)
    replay_s, csv_s, blf_s = (300.0, 60.0, 15.0) if args.quick else (3600.0, 600.0, 120.0)
    blf_s = args.blf_seconds or blf_s
    fig: dict = {"quick": args.quick, "cpus": os.cpu_count(), "load_average_1min": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        if args.blf_only:
            return _blf_only(fig, blf_s, d, args.json, not args.no_reference)
        fig["replay"] = bench_replay(replay_s, d)
        fig["replay_chunk_4s"] = bench_replay(replay_s / (6 if not args.quick else 1), d, chunk_s=4.0)
        for key in ("replay", "replay_chunk_4s"):
            r = fig[key]
            print(f"replay {r['log_s'] / 60:.0f} min at 2 kHz, chunks of {r['chunk_s']} s: "
                  f"{r['samples_per_s']:,} samples/s through the engine ({r['x_real_time']}x real time; "
                  f"{r['engine_s']} s engine + {r['gen_s']} s generating; "
                  f"{r['samples_per_cpu_s']:,} samples per CPU-second)", file=sys.stderr, flush=True)
        fig["csv_read"] = bench_csv(csv_s, d)
        c = fig["csv_read"]
        print(f"CSV read: {c['samples_per_s']:,} samples/s ({c['samples_per_cpu_s']:,} per CPU-second)",
              file=sys.stderr, flush=True)
        fig["blf_read"] = bench_blf(blf_s, d, not args.no_reference)
        fig["load_average_1min_end"] = os.getloadavg()[0]
        b = fig["blf_read"]
        _print_blf(b)
    _emit(fig, args.json)
    return 0


def _print_blf(b: dict) -> None:
    ref = (f"; frame by frame with can.LogReader: {b['reference_samples_per_s']:,} samples/s; same samples: "
           f"{b['same_as_reference']}") if "reference_samples_per_s" in b else ""
    print(f".blf read ({b['log_s'] / 60:g} min at 2 kHz, {b['frames']:,} frames): {b['samples_per_s']:,} "
          f"samples/s ({b['samples_per_cpu_s']:,} per CPU-second){ref}", file=sys.stderr, flush=True)


def _blf_only(fig: dict, seconds: float, d: Path, out: str | None, reference: bool) -> int:
    fig["blf_read"] = bench_blf(seconds, d, reference)
    fig["load_average_1min_end"] = os.getloadavg()[0]
    _print_blf(fig["blf_read"])
    _emit(fig, out)
    return 0


def _emit(fig: dict, out: str | None) -> None:
    text = json.dumps(fig, indent=1)
    if out == "-":
        print(text)
    elif out:
        Path(out).write_text(text + "\n", encoding="utf-8")


if __name__ == "__main__":
    sys.exit(main())
