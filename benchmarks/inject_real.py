"""Effects injected into shipped real logs at 0.25-0.6 of the noise sigma: how often are they named?

    .venv/bin/python benchmarks/inject_real.py [--json OUT.json]
    .venv/bin/python benchmarks/inject_real.py --power [--logs mikoff_imu0]   # what any test could do

``--power`` asks whether the log can show the effect at all: for each injected signal s (on the used
samples), the part of it the baseline (session offset + nine gravity terms) cannot absorb, as a share
of its energy, and the noncentrality lambda = s' V^-1 s - s' V^-1 X (X' V^-1 X)^-1 X' V^-1 s of the
likelihood-ratio test under the log's fitted error model V (the test's own, ``AxisLR.model``), for an
oracle that knows the effect's shape. Its power at the analysis' threshold (p < 0.01/18, times the
look-elsewhere factor of the warm-up grid or the frequency search) is the most ANY test could name on
that log; the analysis' searched test has less.

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


def _problem(columns: dict, log: LogData):
    """The analysis' problem (used samples, baseline design) and its per-axis tests, as in analyze()."""
    from gyrocal.analysis.baseline import build_problem
    from gyrocal.analysis.candidates import all_candidates
    from gyrocal.analysis.lrtest import build_axis_lr
    from gyrocal.analysis.segments import usable_samples
    from gyrocal.analysis.timestamps import retime
    from gyrocal.model.terms import derived_columns

    cols = derived_columns(retime(columns)[0])
    prob = build_problem(cols, usable_samples(cols))
    cands = all_candidates(prob)
    return prob, [build_axis_lr(prob, cands, k) for k in range(3)]


def power(name: str, sizes: list[float]) -> list[dict]:
    """Oracle power of each injection on one log (see the module docstring)."""
    from scipy import stats

    from gyrocal.analysis.baseline import gram_solve
    from gyrocal.analysis.gls import StateSpaceGLS
    from gyrocal.analysis.holdout import ALPHA

    log = LOGS[name]()
    clean = analyze(log).result
    sigma = float(np.mean(list(clean["noise_dps"].values())))
    t = log.columns["t"]
    span = float(t.max() - t.min())
    prob0, lrs = _problem(log.columns, log)
    rows = []
    for size in sizes:
        for cause, axis, amp, params, look, dof in (
            ("warmup", "x", size * sigma, {"tau_s": 60.0}, 8.0, 1),
            ("periodic", "y", size * sigma * np.sqrt(2), {"frequency_hz": 1.7},
             max(1.0, (0.45 * prob0.rate_hz - 0.15) * span), 2),
            ("random_walk", "z", size * sigma / np.sqrt(span / 2), {}, 1.0, 1),
        ):
            k = "xyz".index(axis)
            w = f"w{axis}"
            full = inject(log.columns, cause, amp, [axis], seed=7, **params)[w] - log.columns[w]
            sig = full[prob0.usable.index]  # on the clean log's used samples (the same still detection)
            x = prob0.base
            b, *_ = np.linalg.lstsq(x, sig, rcond=None)
            outside = float(np.sum((sig - x @ b) ** 2) / np.sum(sig**2))
            gls = StateSpaceGLS(lrs[k].model, prob0.cols["t"], prob0.usable.session)
            g = gls.gram(np.column_stack([x, sig]))
            beta = gram_solve(g[:-1, :-1], g[:-1, -1], prob0.n)
            lam = float(g[-1, -1] - g[:-1, -1] @ beta)
            crit = stats.chi2.isf(ALPHA / look, dof)
            pw = float(stats.ncx2.sf(crit, dof, max(lam, 1e-12)))
            rows.append({"log": name, "cause": cause, "size_sigma": size,
                         "outside_baseline": round(outside, 3), "lambda": round(lam, 2),
                         "critical": round(float(crit), 1), "oracle_power": round(pw, 3)})
            print(json.dumps(rows[-1]), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json")
    ap.add_argument("--power", action="store_true", help="oracle power of each injection (no search)")
    ap.add_argument("--sizes", default="0.25,0.4,0.6")
    ap.add_argument("--logs", default=",".join(LOGS), help="comma-separated subset of " + ", ".join(LOGS))
    args = ap.parse_args()
    if args.power:
        sizes = [float(x) for x in args.sizes.split(",")]
        prow = [r for name in args.logs.split(",") for r in power(name, sizes)]
        if args.json:
            with open(args.json, "w") as fh:
                json.dump({"power": prow}, fh, indent=1)
        return
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
