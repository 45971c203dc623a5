"""The walk test's null distribution on simulated null logs (issue 12, s12walk).

    .venv/bin/python benchmarks/walk_null_calibration.py --kinds white,coloured,quantised --seeds 34000:34060
    .venv/bin/python benchmarks/walk_null_calibration.py --walk-null allan  # the held level (before s13white)

Per null log and axis, the variance-component likelihood ratio of ``lrtest.walk_lr`` on the
baseline: the share of axes with q_hat = 0 (the boundary mass; 0.5 under the 50:50 chi-bar-square
null), how many p-values fall below 0.05, 0.01 and ALPHA, and the largest D (the critical D at
ALPHA is about 10.6). The kinds are ``hidden.add_background``'s. ``--walk-null`` picks the null's
level: profiled with the walk on block means (``lrtest.WALK_NULL = "profiled"``, the default) or the
Allan fit's, held ("allan").
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from gyrocal.analysis import lrtest
from gyrocal.analysis.candidates import all_candidates
from gyrocal.analysis.engine import problem_of
from gyrocal.analysis.hidden import add_background, generate
from gyrocal.analysis.holdout import ALPHA
from gyrocal.analysis.lrtest import build_axis_lr, walk_lr


def calibrate(kind: str, seeds: range) -> dict:
    d, p = [], []
    for seed in seeds:
        cols, _ = generate(seed, causes=[])
        cols = add_background(cols, kind, seed)
        prob = problem_of(cols)
        cands = all_candidates(prob)
        for k in range(3):
            w = walk_lr(build_axis_lr(prob, cands, k), [])
            d.append(w.d)
            p.append(w.p_value)
    d_a, p_a = np.array(d), np.array(p)
    return {"kind": kind, "axes": int(d_a.size), "q_hat_zero_share": round(float(np.mean(d_a == 0)), 3),
            "p_below_0.05": int(np.sum(p_a < 0.05)), "p_below_0.01": int(np.sum(p_a < 0.01)),
            "p_below_alpha": int(np.sum(p_a < ALPHA)), "max_d": round(float(d_a.max()), 2)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kinds", default="white,coloured,quantised")
    ap.add_argument("--seeds", default="34000:34060", help="first:last (exclusive)")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--walk-null", choices=("profiled", "allan"),
                    help="the walk test's null level (lrtest.WALK_NULL; default: the module's)")
    args = ap.parse_args(argv)
    if args.walk_null:
        lrtest.WALK_NULL = args.walk_null
    a, b = (int(s) for s in args.seeds.split(":"))
    out = []
    for kind in args.kinds.split(","):
        out.append(calibrate(kind, range(a, b)))
        print(json.dumps(out[-1]), flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
