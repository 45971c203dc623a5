"""Decode and encode throughput of the unit's wire protocol [frames/s and samples/s].

Serial: a stream of SAMPLE frames fed to FrameDecoder in 4 KiB reads (what a reader thread gets).
CAN: SAMPLE_A/B/C frames (plus anchors) fed one can.Message at a time to CanDecoder.
Encode: encode_frame / CanCodec.encode per sample. The 2 kHz target needs 2000 samples/s with room
to spare for the estimator, i.e. samples/s here should be >> 2000. No asserts on time: it prints.

    .venv/bin/python benchmarks/bench_decode.py [--samples N] [--repeat R] [--json]
"""

from __future__ import annotations

import argparse
import json
import platform
import random
import time
from collections.abc import Callable

from gyrocal.protocol.can_codec import CanCodec
from gyrocal.protocol.messages import Sample
from gyrocal.protocol.serial_framing import FrameDecoder, encode_frame


def make_samples(n: int, seed: int = 0) -> list[Sample]:
    """n consecutive 2 kHz samples with realistic magnitudes, seeded."""
    r = random.Random(seed)
    return [Sample(i, i * 500e-6, (r.gauss(0, 0.05), r.gauss(0, 0.05), r.gauss(0, 0.05)),
                   (r.gauss(0, 0.01), r.gauss(0, 0.01), 1.0 + r.gauss(0, 0.01)), 25.0 + i * 1e-5)
            for i in range(n)]


def best_of(repeat: int, fn: Callable[[], int]) -> tuple[float, int]:
    """(shortest wall time [s], count returned) over repeat runs."""
    best, count = float("inf"), 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        count = fn()
        best = min(best, time.perf_counter() - t0)
    return best, count


def run(n: int, repeat: int) -> dict[str, dict[str, float]]:
    samples = make_samples(n)
    stream = b"".join(encode_frame(s) for s in samples)
    codec = CanCodec()
    can_frames = [f for s in samples for f in codec.encode(s)]

    def serial_decode() -> int:
        dec = FrameDecoder()
        got = 0
        for i in range(0, len(stream), 4096):
            got += len(dec.feed(stream[i : i + 4096]))
        return got

    def can_decode() -> int:
        dec = codec.decoder()
        got = 0
        for f in can_frames:
            got += len(dec.feed(f))
        return got

    def serial_encode() -> int:
        for s in samples:
            encode_frame(s)
        return n

    def can_encode() -> int:
        enc = CanCodec()
        for s in samples:
            enc.encode(s)
        return n

    results = {}
    for name, fn, frames_per_sample in (
        ("serial_decode", serial_decode, 1.0),
        ("can_decode", can_decode, len(can_frames) / n),
        ("serial_encode", serial_encode, 1.0),
        ("can_encode", can_encode, len(can_frames) / n),
    ):
        secs, count = best_of(repeat, fn)
        if count != n:
            raise SystemExit(f"{name}: got {count} samples of {n}")
        results[name] = {"samples_per_s": n / secs, "frames_per_s": n * frames_per_sample / secs,
                         "us_per_sample": 1e6 * secs / n, "samples": n}
    return results


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=20000, help="samples per run (default 20000)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per case; the best is kept (default 3)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = ap.parse_args()
    results = run(args.samples, args.repeat)
    if args.json:
        print(json.dumps({"python": platform.python_version(), "machine": platform.machine(),
                          "results": results}, indent=2))
        return 0
    head = f"{'case':<15}{'frames/s':>12}{'samples/s':>12}{'us/sample':>11}"
    print(f"{head}  (python {platform.python_version()}, {args.samples} samples, best of {args.repeat})")
    for name, r in results.items():
        print(f"{name:<15}{r['frames_per_s']:>12,.0f}{r['samples_per_s']:>12,.0f}{r['us_per_sample']:>11.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
