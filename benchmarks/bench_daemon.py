"""The daemon end to end: samples/s with no sample lost, sample-to-weights latency, memory over a soak.

    .venv/bin/python benchmarks/bench_daemon.py [--seconds 20] [--soak-s 60] [--rate 2000] [--json]
                                                [--skip-can] [--small-still-s 0.02]

Everything runs through the real daemon engine (``gyrocal.daemon.engine.Engine``: link reader
thread -> ring buffer -> still detector -> session -> estimator, control socket, store) against the
virtual unit (``gyrocal sim``) as a separate process, wired the way ``gyrocal demo`` wires them: on a
pty, and on a python-can ``udp_multicast`` bus (the engine listens first there). benchmarks/bench_link.py
measures the link alone at its limit; this one measures the whole daemon at the unit's highest rate.

1. throughput: the unit runs ``--duration SECONDS`` at ``--rate`` (default 2000 Hz, the config's
   maximum), so it sends exactly round(SECONDS x rate) samples and then writes its final status.
   Compared: what the unit sent (its status ``samples_sent``) with what the engine received
   (``ring.pushed``), lost in the ring (``ring.lost``), the decoder's sequence gaps
   (``link.stats()['errors']['lost_samples']``) and seq breaks the engine saw in what it popped.
   ``no_sample_lost`` is reported, never asserted. On a pty, pyserial flushes the input buffer when
   the daemon opens the port, so samples the unit sent before that (the seq of the first sample
   received) are reported apart and not counted as lost, as with a unit switched on before the host.
   samples/s = received / (last rx - first rx); cpu = the daemon process's CPU time / wall time.
2. latency: ``Engine.latency_percentiles_s()`` (p50 / p99 / max over the newest 16384 samples,
   ~8 s at 2 kHz) at the end of each run: from a sample's arrival at the host (the reader thread's
   ``rx`` stamp) until the engine handed it to the session (``Session.feed``, which updates the
   weights). It includes the still detector's look-ahead, half its window (``still.window_s`` 0.2 s
   = 0.1 s at the detector's rate), because a sample is only decided once the samples after it have
   arrived. The runs with ``still.window_s`` = ``--small-still-s`` (default 0.02 s) shrink that
   look-ahead so the rest (batching in the unit, the engine's 2 ms poll, processing) shows; the
   look-ahead actually in effect (detector half-window in samples / unit rate) is reported next to
   each figure, with the rate the session was sized for: the engine sizes the detector in samples
   from the rate it assumes when the session starts (``session_rate_hz``), which may differ from the
   unit's rate (``hello_rate_hz``), and then the look-ahead differs from half of ``still.window_s``.
3. memory: a fresh Python process (this script with ``--soak-child``) runs the engine against the
   unit on a pty at ``--rate`` for ``--soak-s`` seconds (600 = the 10-minute soak) and reads its
   own VmRSS from /proc/self/status at the start (after the engine opened) and every ``--rss-every``
   seconds; reported: start, end, max, and the slope [kB/min] of a least-squares line over the
   second half of the soak (the first half includes the first calibration, push and monitoring).

Figures only: nothing here asserts on time or memory.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gyrocal.daemon.config import load_config  # noqa: E402
from gyrocal.daemon.engine import Engine  # noqa: E402
from gyrocal.daemon.virtual import VirtualUnitProcess, free_udp_port, start_virtual_unit  # noqa: E402

CAN_CHANNEL = "239.74.163.2"


def rss_kb(pid: int | str = "self") -> int:
    """VmRSS [kB] of a process from /proc (0 when it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def cpu_s(pid: int | str = "self") -> float:
    """User + system CPU time [s] of a process from /proc/PID/stat (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class BenchEngine(Engine):
    """The daemon's engine, plus a check of the seq continuity of every block it pops."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.first_seq: int | None = None
        self.next_seq: int | None = None
        self.seq_breaks = 0
        self.first_rx = self.last_rx = 0.0

    def _on_samples(self, block: np.ndarray, now: float) -> None:
        seq = block["seq"].astype(np.int64)
        if self.first_seq is None:
            self.first_seq, self.first_rx = int(seq[0]), float(block["rx"][0])
        elif seq[0] != self.next_seq:
            self.seq_breaks += 1
        self.seq_breaks += int(np.count_nonzero(np.diff(seq) != 1))
        self.next_seq, self.last_rx = int(seq[-1]) + 1, float(block["rx"][-1])
        super()._on_samples(block, now)


@contextmanager
def daemon_and_unit(kind: str, rate: float, work: Path, overrides: dict[str, Any] | None = None,
                    unit_args: list[str] | None = None) -> Iterator[tuple[BenchEngine, VirtualUnitProcess]]:
    """An opened engine and a running virtual unit, connected as ``gyrocal demo`` connects them."""
    cfg = load_config(None, {
        "state_dir": str(work / "state"), "control_socket": str(work / "control.sock"),
        "virtual_unit.seed": 1, "virtual_unit.rate_hz": rate, "link.kind": kind, **(overrides or {}),
    })
    unit = engine = None
    try:
        if kind == "can":  # on a bus, listen before the unit switches on, or its HELLO goes unheard
            port = free_udp_port()
            engine = BenchEngine(cfg, {**cfg.link, "kind": "can",
                                       "can": {"interface": "udp_multicast", "channel": CAN_CHANNEL,
                                               "port": port}})
            engine.open()
            unit = start_virtual_unit(cfg.virtual_unit, kind, work / "unit", extra=unit_args, can_port=port)
        else:
            unit = start_virtual_unit(cfg.virtual_unit, kind, work / "unit", extra=unit_args)
            engine = BenchEngine(cfg, {**cfg.link, **unit.link_cfg})
            engine.open()
        yield engine, unit
    finally:
        if engine is not None:
            engine.close()
        if unit is not None:
            unit.stop()


def _final_unit_status(unit: VirtualUnitProcess, timeout_s: float = 5.0) -> dict[str, Any]:
    end = time.monotonic() + timeout_s
    st = unit.status()
    while st.get("running", True) and time.monotonic() < end:
        time.sleep(0.05)
        st = unit.status()
    return st


def _latency(engine: Engine, rate: float) -> dict[str, Any]:
    lat = engine.latency_percentiles_s()
    ahead_s = engine.detector.lookahead_s
    return {**lat, "still_window_samples": round(engine.detector.rule.window_s * rate),
            "lookahead_samples": round(ahead_s * rate), "lookahead_s": ahead_s,
            "session_rate_hz": None if engine.session is None else engine.session.rate_hz,
            "engine_rate_hz": engine.rate_hz,
            "hello_rate_hz": None if engine.last_hello is None else engine.last_hello.rate_hz}


def bench_throughput(kind: str, rate: float, seconds: float, still_window_s: float | None) -> dict[str, Any]:
    """One run of ``seconds`` worth of samples at ``rate``: counts, samples/s, CPU and latency."""
    total = round(seconds * rate)
    overrides = {} if still_window_s is None else {"still.window_s": still_window_s}
    unit_args = ["--duration", f"{seconds:g}"]
    with tempfile.TemporaryDirectory(prefix="gyrocal-bench-") as tmp, \
            daemon_and_unit(kind, rate, Path(tmp), overrides, unit_args) as (engine, unit):
        t0, c0 = time.monotonic(), time.process_time()
        next_check = [0.0]

        def done(e: Engine) -> bool:
            if engine.next_seq is not None and engine.next_seq >= total:
                return True  # the unit's last sample went through the engine
            now = time.monotonic()
            if now >= next_check[0]:  # a unit that stopped early (or a lost tail): stop too
                next_check[0] = now + 0.25
                return unit.proc.poll() is not None or unit.status().get("running") is False
            return False

        engine.run(until=done, timeout_s=seconds + 30.0)
        wall, cpu = time.monotonic() - t0, time.process_time() - c0
        ring = {"pushed": engine.ring.pushed, "popped": engine.ring.popped, "lost": engine.ring.lost}
        link = engine.link.stats()
        lat = _latency(engine, rate)
        state = engine.session.state.value if engine.session is not None else "WAIT_HELLO"
        pushed = bool(engine.session is not None and engine.session.last_push)
        first_seq, seq_breaks = engine.first_seq, engine.seq_breaks
        span = engine.last_rx - engine.first_rx
        ust = _final_unit_status(unit)
        unit_cpu = cpu_s(unit.proc.pid)
    sent = int(ust.get("samples_sent", -1))
    transport = ust.get("transport") or {}
    tx_dropped = int(transport.get("tx_dropped_frames", 0)) + int(transport.get("tx_errors", 0))
    before = first_seq or 0
    expected = sent - before
    errors = link.get("errors", {})
    lost = {"ring_lost": ring["lost"], "decoder_lost_samples": int(errors.get("lost_samples", 0)),
            "decoder_seq_gaps": int(errors.get("seq_gaps", 0)), "engine_seq_breaks": seq_breaks,
            "unit_tx_dropped": tx_dropped, "missing": expected - ring["pushed"]}
    return {
        "link": kind, "rate_hz": rate, "seconds": seconds, "still_window_s": still_window_s or 0.2,
        "unit_sent": sent, "sent_before_daemon_listened": before, "expected": expected,
        "received": ring["pushed"], "ring": ring, "lost": lost,
        "no_sample_lost": sent == total and expected == ring["pushed"] and not any(
            v for k, v in lost.items() if k != "decoder_seq_gaps"),
        "samples_per_s": (ring["pushed"] - 1) / span if span > 0 else 0.0,
        "daemon_cpu_fraction": cpu / wall, "unit_cpu_s": unit_cpu, "wall_s": wall,
        "latency_s": lat, "state": state, "pushed": pushed,
        "decoder_errors": {k: v for k, v in errors.items() if v and k not in ("seq_gaps", "lost_samples")},
    }


def soak(rate: float, soak_s: float, every_s: float) -> dict[str, Any]:
    """Run the engine on a pty at ``rate`` for ``soak_s`` [s]; this process's VmRSS every ``every_s``."""
    rss_before = rss_kb()
    with tempfile.TemporaryDirectory(prefix="gyrocal-soak-") as tmp, \
            daemon_and_unit("serial", rate, Path(tmp)) as (engine, unit):
        t0 = time.monotonic()
        samples: list[tuple[float, int]] = [(0.0, rss_kb())]
        unit_rss = [rss_kb(unit.proc.pid)]
        nxt = [t0 + every_s]

        def sample(e: Engine) -> bool:
            now = time.monotonic()
            if now >= nxt[0]:
                nxt[0] += every_s
                samples.append((now - t0, rss_kb()))
                unit_rss.append(rss_kb(unit.proc.pid))
            return False

        engine.run(until=sample, timeout_s=soak_s)
        if samples[-1][0] < soak_s - 1.0:
            samples.append((time.monotonic() - t0, rss_kb()))
        ring = {"pushed": engine.ring.pushed, "popped": engine.ring.popped, "lost": engine.ring.lost}
        errors = engine.link.stats().get("errors", {})
        s = engine.session
        status = {"state": s.state.value if s else "WAIT_HELLO", "last_push": s.last_push if s else {},
                  "alarm": bool(s and s.alarm), "sessions": engine.sessions_started,
                  "store_versions": [r.version for r in engine.store.history(s.hello.serial)] if s else []}
        sent_approx = int(unit.status().get("samples_sent", -1))
        lat = _latency(engine, rate)
    t = np.array([p[0] for p in samples])
    kb = np.array([p[1] for p in samples], dtype=float)
    half = t >= soak_s / 2
    slope = float(np.polyfit(t[half], kb[half], 1)[0] * 60.0) if half.sum() >= 2 else float("nan")
    return {
        "link": "serial", "rate_hz": rate, "soak_s": soak_s, "every_s": every_s,
        "rss_kb_before_engine": rss_before, "rss_kb_start": int(kb[0]), "rss_kb_end": int(kb[-1]),
        "rss_kb_max": int(kb.max()), "slope_kb_per_min_second_half": slope,
        "rss_series": [[round(a, 1), int(b)] for a, b in samples],
        "unit_rss_kb_start": unit_rss[0], "unit_rss_kb_end": unit_rss[-1],
        "received": ring["pushed"], "unit_sent_approx": sent_approx, "ring_lost": ring["lost"],
        "decoder_lost_samples": int(errors.get("lost_samples", 0)),
        "latency_s": lat, **status,
    }


def soak_in_fresh_process(rate: float, soak_s: float, every_s: float) -> dict[str, Any]:
    """Run ``soak`` in a new interpreter, so earlier runs leave nothing in the measured heap."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--soak-child", "--rate", str(rate),
           "--soak-s", str(soak_s), "--rss-every", str(every_s)]
    out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=soak_s + 120, check=True)
    return json.loads(out.stdout)


def _ms(v: Any) -> str:
    return f"{v * 1e3:8.1f}" if isinstance(v, float) else f"{'-':>8}"


def print_table(report: dict[str, Any]) -> None:
    h = report["host"]
    print(f"gyrocal daemon benchmark: python {h['python']}, {h['machine']}, {h['cpus']} cpus, "
          f"load {h['load_avg_1min']:.2f}")
    print("\n1. end-to-end throughput: virtual unit (separate process) -> link -> daemon engine")
    print(f"{'link':<7}{'still':>6}{'rate Hz':>8}{'sent':>9}{'pre-open':>9}{'received':>9}{'lost':>6}"
          f"{'samples/s':>11}{'no loss':>8}{'cpu':>6}")
    for r in report["throughput"]:
        lost = r["lost"]
        n_lost = max(lost["missing"], lost["ring_lost"] + lost["decoder_lost_samples"])
        n_lost += lost["unit_tx_dropped"]
        print(f"{r['link']:<7}{r['still_window_s']:>6g}{r['rate_hz']:>8g}{r['unit_sent']:>9}"
              f"{r['sent_before_daemon_listened']:>9}{r['received']:>9}{n_lost:>6}{r['samples_per_s']:>11,.1f}"
              f"{'yes' if r['no_sample_lost'] else 'NO':>8}{r['daemon_cpu_fraction']:>6.0%}")
    print("   pre-open = samples the unit sent before the daemon opened the port (pyserial flushes them)")
    print("\n2. sample-to-weights latency [ms] (newest <=16384 samples of each run)")
    print(f"{'link':<7}{'still s':>8}{'look-ahead':>11}{'p50':>8}{'p99':>8}{'max':>8}{'p50-look':>9}"
          f"{'n':>7}  detector window")
    for r in report["throughput"]:
        lat = r["latency_s"]
        extra = (lat.get("p50", 0.0) - lat["lookahead_s"]) if "p50" in lat else None
        print(f"{r['link']:<7}{r['still_window_s']:>8g}{_ms(lat['lookahead_s']):>11}{_ms(lat.get('p50'))}"
              f"{_ms(lat.get('p99'))}{_ms(lat.get('max'))}{_ms(extra):>9}{lat.get('n', 0):>7}  "
              f"{lat['still_window_samples']} samples (session assumes {lat['session_rate_hz']} Hz)")
    s = report.get("soak")
    if s:
        print(f"\n3. resident memory of the daemon process, {s['soak_s']:g} s at {s['rate_hz']:g} Hz "
              f"on a pty (VmRSS every {s['every_s']:g} s)")
        print(f"   before engine {s['rss_kb_before_engine']} kB; start {s['rss_kb_start']} kB; "
              f"end {s['rss_kb_end']} kB; max {s['rss_kb_max']} kB; "
              f"slope over the second half {s['slope_kb_per_min_second_half']:+.1f} kB/min")
        print(f"   received {s['received']} samples (unit ~{s['unit_sent_approx']}), ring lost "
              f"{s['ring_lost']}, decoder lost {s['decoder_lost_samples']}; end state {s['state']}, "
              f"store versions {s['store_versions']}")
        series = " ".join(f"{t:.0f}s:{kb}" for t, kb in s["rss_series"])
        print(f"   VmRSS [kB] series: {series}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=20.0, help="seconds per throughput run (default 20)")
    p.add_argument("--soak-s", type=float, default=60.0, help="memory soak [s]; 600 = 10 min; 0 = skip")
    p.add_argument("--rss-every", type=float, default=10.0, help="RSS sampling interval in the soak [s]")
    p.add_argument("--rate", type=float, default=2000.0, help="the unit's sample rate [Hz], at most 2000")
    p.add_argument("--small-still-s", type=float, default=0.02,
                   help="still.window_s of the extra latency runs (0 = no extra runs)")
    p.add_argument("--skip-can", action="store_true", help="only the pty link")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--soak-child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.soak_child:
        print(json.dumps(soak(args.rate, args.soak_s, args.rss_every)))
        return 0
    kinds = ["serial"] if args.skip_can else ["serial", "can"]
    windows: list[float | None] = [None] + ([args.small_still_s] if args.small_still_s > 0 else [])
    report: dict[str, Any] = {
        "host": {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count(),
                 "load_avg_1min": os.getloadavg()[0]},
        "throughput": [bench_throughput(k, args.rate, args.seconds, w) for w in windows for k in kinds],
    }
    if args.soak_s > 0:
        report["soak"] = soak_in_fresh_process(args.rate, args.soak_s, args.rss_every)
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        print_table(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
