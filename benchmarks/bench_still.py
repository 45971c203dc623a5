"""Throughput of the on-line still detector (model/still.py), the daemon's per-sample hot path.

Prints samples per second fed in 0.1 s chunks at a given rate, and the share of one core that rate
costs. ``--json`` for the same as JSON.

    python benchmarks/bench_still.py [--rate 2000] [--seconds 100] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from gyrocal.daemon.ring import SAMPLE_DTYPE
from gyrocal.model.still import StreamingStill


def run(rate_hz: float, seconds: float, seed: int = 1) -> dict[str, float]:
    n = int(rate_hz * seconds)
    rng = np.random.default_rng(seed)
    b = np.zeros(n, dtype=SAMPLE_DTYPE)
    b["t"] = np.arange(n) / rate_hz
    for f in ("wx", "wy", "wz"):
        b[f] = rng.normal(0.0, 0.01, n)  # deg/s
    for f in ("ax", "ay", "az"):
        b[f] = rng.normal(0.0, 0.002, n) + (f == "az")  # g
    det = StreamingStill(rate_hz)
    chunk = max(1, int(rate_hz / 10))
    t0 = time.perf_counter()
    for i in range(0, n, chunk):
        det.feed(b[i:i + chunk])
    wall = time.perf_counter() - t0
    return {"rate_hz": rate_hz, "samples": n, "wall_s": round(wall, 3),
            "samples_per_s": round(n / wall), "core_share": round(rate_hz * wall / n, 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=2000.0, help="sample rate [Hz] (default 2000)")
    ap.add_argument("--seconds", type=float, default=100.0, help="seconds of samples (default 100)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of a line")
    args = ap.parse_args()
    r = run(args.rate, args.seconds)
    if args.json:
        print(json.dumps(r))
    else:
        print(f"{r['samples']} samples at {r['rate_hz']:g} Hz in {r['wall_s']} s: "
              f"{r['samples_per_s']} samples/s, {100 * r['core_share']:.2f} % of a core")


if __name__ == "__main__":
    main()
