"""Throughput of the link to the unit: protocol decoding alone, then end to end with no sample lost.

    .venv/bin/python benchmarks/bench_link.py [--samples N] [--json]

1. decode: ``FrameDecoder.feed`` over pre-encoded serial SAMPLE frames (fed 4 KiB at a time) and
   ``CanDecoder.feed`` over pre-encoded CAN frames [frames/s and samples/s, one core, no I/O].
2. serial_pty: a forked producer writes pre-encoded frames into a pty master as fast as the kernel
   takes them (the pty pushes back, so nothing is dropped on the way); ``SerialLink`` reads the slave
   into a ``RingBuffer`` that the main thread drains. Samples/s from the first to the last sample.
3. can_virtual: a producer thread sends pre-encoded frames on a python-can ``virtual`` bus in this
   process; ``CanLink`` reads them (both share one GIL, so this is a lower bound).
4. can_udp_multicast: a forked producer sends at a paced rate [samples/s] on ``udp_multicast`` (no
   push-back: UDP drops when the reader falls behind); each rate runs ``--udp-seconds``. Reports the
   highest rate with no sample lost.

Every end-to-end run checks that the samples arrived complete and in order (seq 0..N-1).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import socket
import sys
import time
from typing import Any

import numpy as np

from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers import CanLink, SerialLink
from gyrocal.protocol.can_codec import CanCodec
from gyrocal.protocol.serial_framing import FrameDecoder, encode_frame
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import TruthModel
from gyrocal.sim.unit import VirtualUnit

GROUP = "239.74.163.2"


def make_samples(n: int, rate_hz: float = 2000.0) -> list[Any]:
    unit = VirtualUnit(TruthModel(), tumble(), rate_hz, seed=1, serial=1)
    unit.power_on()
    out: list[Any] = []
    while len(out) < n:
        out.extend(unit.samples(min(20_000, n - len(out))))
    return out


def bench_decode(samples: list[Any]) -> dict[str, float]:
    blob = b"".join(encode_frame(s) for s in samples)
    dec = FrameDecoder()
    t0 = time.perf_counter()
    got = sum(len(dec.feed(blob[i : i + 4096])) for i in range(0, len(blob), 4096))
    dt_serial = time.perf_counter() - t0
    codec = CanCodec()
    frames = [f for s in samples for f in codec.encode(s)]
    cdec = codec.decoder()
    t0 = time.perf_counter()
    cgot = sum(len(cdec.feed(f)) for f in frames)
    dt_can = time.perf_counter() - t0
    if got != len(samples) or cgot != len(samples):
        raise SystemExit(f"decode lost samples: serial {got}, can {cgot} of {len(samples)}")
    return {"serial_frames_per_s": got / dt_serial, "serial_mbyte_per_s": len(blob) / dt_serial / 1e6,
            "can_frames_per_s": len(frames) / dt_can, "can_samples_per_s": cgot / dt_can,
            "can_frames_per_sample": len(frames) / len(samples)}


def _drain(ring: RingBuffer, n: int, timeout_s: float) -> tuple[np.ndarray, float, float]:
    """Pop until n samples arrived; returns (samples, first rx time, last rx time)."""
    chunks, end = [], time.monotonic() + timeout_s
    count = 0
    while count < n and time.monotonic() < end:
        c = ring.pop()
        if len(c):
            chunks.append(c)
            count += len(c)
        else:
            time.sleep(0.005)
    out = np.concatenate(chunks) if chunks else np.empty(0, dtype=ring.pop().dtype)
    if len(out) == 0:
        return out, 0.0, 0.0
    return out, float(out["rx"][0]), float(out["rx"][-1])


def _result(out: np.ndarray, n: int, t_first: float, t_last: float, ring: RingBuffer, st: dict) -> dict:
    in_order = len(out) == n and bool(np.all(out["seq"].astype(np.int64) == np.arange(n)))
    return {"samples": n, "received": int(len(out)), "complete_in_order": in_order, "ring_lost": ring.lost,
            "samples_per_s": (len(out) - 1) / (t_last - t_first) if t_last > t_first else 0.0,
            "decoder_errors": {k: v for k, v in st["errors"].items() if v}}


def _pty_writer(master: int, blob: bytes, go: Any) -> None:
    go.wait()
    view = memoryview(blob)
    while view:
        n = os.write(master, view[:65536])
        view = view[n:]
    time.sleep(5)  # keep the master open until the reader has the tail


def bench_serial_pty(samples: list[Any]) -> dict[str, Any]:
    import tty

    blob = b"".join(encode_frame(s) for s in samples)
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    ctx = mp.get_context("fork")
    go = ctx.Event()
    proc = ctx.Process(target=_pty_writer, args=(master, blob, go), daemon=True)
    proc.start()
    ring = RingBuffer(1 << 16)
    link = SerialLink(path, ring, lambda m: None)
    link.start()
    try:
        go.set()
        out, t0, t1 = _drain(ring, len(samples), 120)
        st = link.stats()
    finally:
        link.stop()
        proc.terminate()
        proc.join()
        os.close(master)
        os.close(slave)
    return _result(out, len(samples), t0, t1, ring, st)


def bench_can_virtual(samples: list[Any]) -> dict[str, Any]:
    import threading

    import can

    codec = CanCodec()
    frames = [f for s in samples for f in codec.encode(s)]
    channel = f"bench-{os.getpid()}"
    ring = RingBuffer(1 << 16)
    link = CanLink({"interface": "virtual", "channel": channel}, ring, lambda m: None)
    link.start()
    bus = can.Bus(interface="virtual", channel=channel)

    def produce() -> None:
        for f in frames:
            bus.send(f)

    th = threading.Thread(target=produce)
    try:
        th.start()
        out, t0, t1 = _drain(ring, len(samples), 120)
        th.join()
        st = link.stats()
    finally:
        link.stop()
        bus.shutdown()
    res = _result(out, len(samples), t0, t1, ring, st)
    res["frames_per_s"] = res["samples_per_s"] * len(frames) / len(samples)
    return res


def _udp_sender(port: int, frames_by_sample: list[list[Any]], rate_hz: float, go: Any) -> None:
    import can

    bus = can.Bus(interface="udp_multicast", channel=GROUP, port=port)
    go.wait()
    t0, i, n = time.monotonic(), 0, len(frames_by_sample)
    while i < n:
        due = min(n, int((time.monotonic() - t0) * rate_hz) + 1)
        for k in range(i, due):
            for f in frames_by_sample[k]:
                bus.send(f)
        i = due
        time.sleep(0.002)
    time.sleep(1.0)
    bus.shutdown()


def bench_can_udp(rates: list[float], seconds: float) -> dict[str, Any]:
    trials = []
    for rate in rates:
        n = int(rate * seconds)
        codec = CanCodec()
        by_sample = [codec.encode(s) for s in make_samples(n, rate)]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("", 0))
            port = s.getsockname()[1]
        ctx = mp.get_context("fork")
        go = ctx.Event()
        proc = ctx.Process(target=_udp_sender, args=(port, by_sample, rate, go), daemon=True)
        proc.start()
        ring = RingBuffer(1 << 16)
        link = CanLink({"interface": "udp_multicast", "channel": GROUP, "port": port}, ring, lambda m: None)
        link.start()
        time.sleep(0.3)  # the sender's socket joins the group
        try:
            go.set()
            out, t0, t1 = _drain(ring, n, seconds + 10)
            st = link.stats()
        finally:
            link.stop()
            proc.join(10)
        res = _result(out, n, t0, t1, ring, st)
        res["rate_hz"] = rate
        trials.append(res)
        if not res["complete_in_order"]:
            break
    ok = [t["rate_hz"] for t in trials if t["complete_in_order"]]
    return {"max_lossless_rate_hz": max(ok) if ok else 0.0, "trials": trials}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=100_000, help="samples per run (default 100000)")
    p.add_argument("--udp-rates", default="2000,4000,8000,16000,32000", help="paced rates to try [samples/s]")
    p.add_argument("--udp-seconds", type=float, default=3.0, help="seconds per udp_multicast rate")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args()
    samples = make_samples(args.samples)
    report = {
        "host": {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count(),
                 "load_avg_1min": os.getloadavg()[0]},
        "decode": bench_decode(samples),
        "serial_pty": bench_serial_pty(samples),
        "can_virtual": bench_can_virtual(samples[: args.samples // 2]),
        "can_udp_multicast": bench_can_udp([float(r) for r in args.udp_rates.split(",")], args.udp_seconds),
    }
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        d = report["decode"]
        print(f"decode  serial {d['serial_frames_per_s']:,.0f} frames/s "
              f"({d['serial_mbyte_per_s']:.1f} MB/s); CAN {d['can_frames_per_s']:,.0f} frames/s "
              f"= {d['can_samples_per_s']:,.0f} samples/s")
        for name in ("serial_pty", "can_virtual"):
            r = report[name]
            print(f"{name:12s} {r['samples_per_s']:,.0f} samples/s end to end, complete and in order: "
                  f"{r['complete_in_order']} ({r['received']}/{r['samples']})")
        u = report["can_udp_multicast"]
        tried = ", ".join(f"{t['rate_hz']:,.0f}:{'ok' if t['complete_in_order'] else 'LOSS'}"
                          for t in u["trials"])
        print(f"udp_multicast highest paced rate with no sample lost: {u['max_lossless_rate_hz']:,.0f} "
              f"samples/s (tried {tried})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
