"""The covariates' test against the walk, calibrated by a parametric bootstrap under the walk.

``lrtest.test_against_walk`` refers its likelihood ratio D (the covariate's columns added, the walk
intensity and the white level profiled by maximum likelihood under both hypotheses) to chi-square.
That is the large-sample law; on a short log it does not hold when the wander really is a walk. The
walk's intensity is read from the few low-frequency degrees of freedom the baseline leaves (a
session offset and nine gravity terms, which on a tumble absorb much of a walk), ML reads it low,
and a slow covariate column (a warm-up, a temperature course) then takes a part of one walk path
for itself. Measured on mikoff imu2 y (160 s, one session, 208 block means; 400 walk + white draws
of the 0.6 sigma injection's intensity on the log's own times and design, a /tmp probe): D of a
warm-up at 5-40 s had a mean of 2.6-4.0 per tau where chi-square(1) has 1, and 6.5 % of the draws
passed the gate (0.01 / 18 with the grid's factor 9, nominal 0.056 %). So a walk injected there was
named warmup (the 2026-11-28 injection run), a wrong cause.

Here the statistic is referred to its own distribution under the fitted null instead: block means
(``lrtest.block_means``) are simulated from the model the likelihood assumes, white noise at the
null's level plus a walk of the intensity the walk test estimated given the chosen causes
(``lrtest.walk_lr``, REML), restarted per session; each draw gets the same statistic as the log.
A warm-up enters at its own column and at every tau of the test's grid, the statistic being the
largest D over them (the draws pay for the choice, so no Bonferroni factor is needed). The p-value
is (1 + draws at or above the log's D) / (1 + draws); drawing stops as soon as the answer is known.

Used as a flag, not as the gate (``causes._walk_as_look_alike``): a covariate named instead of the
walk lists ``random_walk`` in ``confounded_with`` when p >= ``FAMILY_ALPHA``. As the gate (tried) it
turned temperature effects on white logs into random_walk findings: there the fitted null is a walk
of the effect's own size, under which a temperature course is an ordinary path.
"""

from __future__ import annotations

import numpy as np

from gyrocal.analysis.baseline import gram_solve
from gyrocal.analysis.candidates import WARMUP_TAUS_S
from gyrocal.analysis.gls import StateSpaceGLS
from gyrocal.analysis.lrtest import AxisLR, block_means, block_size, walk_grid, walk_lr, with_walk
from gyrocal.analysis.noisemodel import NoiseModel

BOOT_DRAWS = 4000
"""Most draws per calibrated test by default (p resolved to 2.5e-4)."""
BOOT_CHUNK = 500
"""Draws simulated at once (their block means share every banded factorisation)."""
BOOT_SEED = 20261128
"""Seed of the draws (fixed: the same log gets the same answer)."""


def _variants(lr: AxisLR, causes: tuple[str, ...]) -> list[np.ndarray]:
    """The alternatives' extra columns (M, k): one set, or, with a warm-up among ``causes``, one per
    warm-up column the test could have chosen (the axis' own and the grid's, as ``lrtest.axis_warmup``)."""
    t_on = lr.prob.cols["t_on"]
    taus = [t for t in WARMUP_TAUS_S if t <= float(np.max(t_on)) / 2] or [WARMUP_TAUS_S[0]]
    warm = [lr.cols["warmup"], *[np.exp(-t_on / t)[:, None] for t in taus]] if "warmup" in causes else [None]
    out = []
    for w in warm:
        out.append(np.column_stack([w if c == "warmup" else lr.cols[c] for c in causes]))
    return out


def _ml_max(gls_by_q: list[StateSpaceGLS], xb: np.ndarray, yb: np.ndarray) -> np.ndarray:
    """The largest ML log-likelihood (K,) over the walk grid of each column of yb on xb (the scale
    profiled out, as ``lrtest.walk_profiled_ml`` without its parabola)."""
    n, p = xb.shape
    best = np.full(yb.shape[1], -np.inf)
    for gls in gls_by_q:
        g = gls.gram(np.column_stack([xb, yb]))
        beta = gram_solve(g[:p, :p], g[:p, p:], n)
        qf = np.maximum(np.diag(g[p:, p:]) - np.einsum("pk,pk->k", g[:p, p:], beta), 1e-300)
        best = np.maximum(best, -0.5 * (n * np.log(qf) + gls.logdet_v))
    return best


def calibrated_p(lr: AxisLR, chosen: list[str], causes: tuple[str, ...], alpha: float,
                 draws: int = BOOT_DRAWS) -> float | None:
    """Bootstrap p-value of adding ``causes`` to ``chosen`` with the walk re-estimated (see the module
    docstring); None when the sessions are too short for block means (the caller keeps the
    chi-square p). At most ``draws`` draws; drawing stops once p is sure to be >= ``alpha`` (the p
    returned is then that of the draws made, at least ``alpha`` up to their sampling error)."""
    from gyrocal.analysis.lrtest import WALK_MIN_BLOCK_SAMPLES

    prob = lr.prob
    m = block_size(prob)
    if m < WALK_MIN_BLOCK_SAMPLES:
        return None
    w = walk_lr(lr, chosen)  # the null: white at its REML level + the walk at its REML intensity
    x0 = lr.design(chosen)
    alts = [np.column_stack([x0, v]) for v in _variants(lr, causes)]
    y = prob.y[:, lr.axis][:, None]
    tb, sb, x0b, yb = block_means(prob, x0, y, m)
    altb = [block_means(prob, x, y, m)[2] for x in alts]
    unit = NoiseModel(w.null.rate_hz / m, w.null.lowfreq_white_var / m, [], 0.0)
    grid = [0.0, *walk_grid(prob, w.null)]
    glss = [StateSpaceGLS(with_walk(unit, q), tb, sb) for q in grid]

    def stat(ys: np.ndarray) -> np.ndarray:
        l0 = _ml_max(glss, x0b, ys)
        return 2.0 * (np.max([_ml_max(glss, xb, ys) for xb in altb], axis=0) - l0)

    d_obs = float(stat(yb)[0])
    start = np.concatenate(([True], sb[1:] != sb[:-1]))
    dt = np.where(start, 0.0, np.maximum(np.diff(tb, prepend=tb[0]), 0.0))
    rng = np.random.default_rng(BOOT_SEED)
    above, done = 0, 0
    while done < draws:
        k = min(BOOT_CHUNK, draws - done)
        steps = rng.normal(0.0, 1.0, (tb.size, k)) * np.sqrt(w.q_hat * dt)[:, None]
        walk = np.empty_like(steps)
        for s0, s1 in zip(np.flatnonzero(start), [*np.flatnonzero(start)[1:], tb.size], strict=True):
            walk[s0:s1] = np.cumsum(steps[s0:s1], axis=0)
        ys = walk + rng.normal(0.0, np.sqrt(unit.white_var), walk.shape)
        above += int(np.sum(stat(ys) >= d_obs))
        done += k
        if (1 + above) / (1 + draws) >= alpha:
            break
    return (1 + above) / (1 + done)
