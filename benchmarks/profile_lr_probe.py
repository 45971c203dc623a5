"""Probe (issue 12, not the shipped test): a likelihood ratio with the slow part re-estimated per hypothesis.

    .venv/bin/python benchmarks/profile_lr_probe.py                      # hard 312, nulls 31053, 32042
    .venv/bin/python benchmarks/profile_lr_probe.py --nulls flicker,real_like --seeds 32000:32010

The shipped test (``lrtest.AxisLR.test``) evaluates D under one error model, fitted by feasible
GLS under the alternative. Here the slow part of the error model (flicker bank + walk, shape from
the Allan fit of the baseline residual, ``point_model_for([])``) is scaled by kappa (0 and 1/16..16,
13 log steps), and kappa is re-estimated by maximum likelihood under each hypothesis:

    l_h = max_kappa -1/2 [ Q_h(kappa) + log det V(kappa) ],   D = 2 (l_1 - l_0)

(ML, not REML: REML likelihoods of different mean models are not comparable). ``StateSpaceGLS``
gives Q and log det V in O(M). Prints, per axis and covariate cause, the shipped p and the profile
p (same look-elsewhere factor).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import stats

from gyrocal.analysis.baseline import Problem, gram_solve
from gyrocal.analysis.candidates import all_candidates
from gyrocal.analysis.engine import problem_of
from gyrocal.analysis.gls import StateSpaceGLS
from gyrocal.analysis.hidden import HardCase, add_background, generate, generate_hard
from gyrocal.analysis.lrtest import build_axis_lr
from gyrocal.analysis.noisemodel import FAST_SAMPLES, NoiseModel

KAPPAS = (0.0, *np.exp(np.linspace(np.log(1 / 16), np.log(16), 13)))
CAUSES = ("warmup", "temperature", "temperature_rate")


def scaled(m: NoiseModel, kappa: float) -> NoiseModel:
    """The model with its slow part (flicker bank + walk) scaled by kappa."""
    gm = [(t, v * (kappa if t * m.rate_hz > FAST_SAMPLES else 1.0)) for t, v in m.gm]
    return NoiseModel(m.rate_hz, m.white_var, gm, m.walk_q * kappa)


def profile(prob: Problem, m: NoiseModel, x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(max over kappa of the Gaussian log-likelihood of y on x, the best kappa)."""
    best, kb = -np.inf, 1.0
    for kappa in KAPPAS:
        gls = StateSpaceGLS(scaled(m, kappa), prob.cols["t"], prob.usable.session)
        g = gls.gram(np.column_stack([x, y]))
        q = g[-1, -1] - g[:-1, -1] @ gram_solve(g[:-1, :-1], g[:-1, -1], prob.n)
        ll = -0.5 * (q + gls.logdet_v)
        if ll > best:
            best, kb = ll, kappa
    return float(best), float(kb)


def probe(cols: dict, label: str) -> list[dict]:
    prob = problem_of(cols)
    cands = all_candidates(prob)
    rows = []
    for k in range(3):
        lr = build_axis_lr(prob, cands, k)
        y = prob.y[:, k]
        m = lr.point_model_for([])
        l0, k0 = profile(prob, m, lr.design([]), y)
        for c in CAUSES:
            if c not in lr.cols:
                continue
            l1, k1 = profile(prob, m, lr.design([c]), y)
            d = 2 * (l1 - l0)
            p = min(1.0, lr.look_elsewhere.get(c, 1.0) * stats.chi2.sf(max(d, 0.0), lr.cols[c].shape[1]))
            rows.append({"log": label, "axis": "xyz"[k], "cause": c, "p_shipped": lr.test([], c)[1],
                         "d_profile": round(d, 2), "p_profile": p, "kappa0": round(k0, 3),
                         "kappa1": round(k1, 3)})
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nulls", help="backgrounds of extra null logs (comma-separated)")
    ap.add_argument("--seeds", default="32000:32010", help="--nulls: first:last seed (exclusive)")
    args = ap.parse_args()
    if args.nulls:
        a, b = (int(s) for s in args.seeds.split(":"))
        for kind in args.nulls.split(","):
            for seed in range(a, b):
                c, _ = generate(seed, causes=[])
                probe(add_background(c, kind, seed), f"null {kind} {seed}")
        return
    cols, _ = generate_hard(HardCase(312, ["warmup"], 0.3, "flicker"))
    probe(cols, "hard 312 (warm-up 0.3 sigma on flicker, x y z)")
    for seed, kind in ((31053, "flicker"), (32042, "real_like")):
        c, _ = generate(seed, causes=[])
        probe(add_background(c, kind, seed), f"null {kind} {seed}")


if __name__ == "__main__":
    main()
