"""Effects injected into shipped real logs at 0.25-0.6 of the noise sigma: how often are they named?

    .venv/bin/python benchmarks/inject_real.py [--json OUT.json]

sigma is the log's per-sample noise (``noise_dps`` of the clean analysis, mean over axes). Warm-up
(tau 60 s, on x), periodic (1.7 Hz, on y) and random walk (intensity such that the walk's RMS over
a session is ``size`` x sigma, on z) are added with ``gyrocal.analysis.hidden.inject``. Named = the
cause appears among the findings on the injected axis; wrong = a regression cause other than the
injected one (or one the clean log did not have) appears.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from gyrocal.analysis.engine import analyze
from gyrocal.analysis.hidden import inject
from gyrocal.datasets._common import data_dir
from gyrocal.datasets.mikoff import load_mikoff
from gyrocal.datasets.tomisuarez import load_tomisuarez
from gyrocal.logformat import LogData

REGRESSION = ("temperature", "temperature_rate", "warmup", "periodic", "scale_factor")
LOGS = {
    "mikoff_imu0": lambda: load_mikoff(data_dir("mikoff_mpu9150") / "imu0.log"),
    "tomi_tinit": lambda: load_tomisuarez(data_dir("tomisuarez_mpu6050") / "example_data_tinit_calc.csv"),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json")
    ap.add_argument("--sizes", default="0.25,0.4,0.6")
    ap.add_argument("--logs", default=",".join(LOGS), help="comma-separated subset of " + ", ".join(LOGS))
    args = ap.parse_args()
    rows = []
    for name in args.logs.split(","):
        log = LOGS[name]()
        clean = analyze(log).result
        base = {f["cause"] for f in clean["findings"]}
        sigma = float(np.mean(list(clean["noise_dps"].values())))
        t = log.columns["t"]
        span = float(t.max() - t.min())
        for size in (float(s) for s in args.sizes.split(",")):
            for cause, axis, amp, params in (
                ("warmup", "x", size * sigma, {"tau_s": 60.0}),
                ("periodic", "y", size * sigma * np.sqrt(2), {"frequency_hz": 1.7}),
                ("random_walk", "z", size * sigma / np.sqrt(span / 2), {}),
            ):
                cols = inject(log.columns, cause, amp, [axis], seed=7, **params)
                r = analyze(LogData(cols, log.metadata, log.extra_columns, log.source)).result
                found = {f["cause"]: f["axes"] for f in r["findings"]}
                named = axis in found.get(cause, [])
                wrong = [c for c in found if c in REGRESSION and c != cause and c not in base]
                rows.append({"log": name, "cause": cause, "size_sigma": size, "named": named, "wrong": wrong,
                             "findings": list(found)})
                print(json.dumps(rows[-1]), flush=True)
    n = len(rows)
    named = sum(r["named"] for r in rows)
    wrong = sum(bool(r["wrong"]) for r in rows)
    print(f"named {named}/{n}, with a wrong cause {wrong}/{n}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"rows": rows, "named": named, "wrong": wrong, "n": n}, fh, indent=1)


if __name__ == "__main__":
    main()
