"""The significance test: a likelihood ratio under the fitted state-space error model.

Why not the old block t-test: it compared held-out blocks as if they were independent, so few
blocks, an effect concentrated in a few blocks, or real flicker (which inflates the spread between
blocks) each defeated it (issue 12). Here the residual's wander is part of the model: per axis the
error model of ``noisemodel`` (white + colour + flicker bank + walk) is fitted to the residual of
the largest model (baseline + every candidate, so a real effect does not inflate the noise), and
each candidate's columns are tested by generalised least squares under it:

    D = Q(model so far) - Q(model so far + candidate),   Q = min_beta (y - X beta)' V^-1 (y - X beta)

D is chi-square with the candidate's parameter count under the null when V is right. ``disp``, the
larger of 1 and Q(all) / (M - rank), guards against a V that is too optimistic: D is divided by it.
A nonlinear choice made on the data pays a look-elsewhere factor (the number of independent
frequencies searched for a periodic cause, the warm-up grid). One Gram matrix x' V^-1 x of every
column serves every nested model, so the whole forward selection costs one banded solve per axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from gyrocal.analysis.baseline import Problem, gram_solve, lstsq
from gyrocal.analysis.candidates import F_MIN_HZ, WARMUP_TAUS_S, Candidate
from gyrocal.analysis.gls import StateSpaceGLS
from gyrocal.analysis.noisemodel import NoiseModel, fit_noise


@dataclass
class AxisLR:
    """Gram matrix of [baseline, every candidate's columns, y] under one axis' error model."""

    gram: np.ndarray
    cols: dict[str, np.ndarray]  # cause -> column indices into gram
    n_base: int
    n: int
    disp: float
    model: NoiseModel
    look_elsewhere: dict[str, float]

    def q(self, causes: list[str]) -> float:
        """Q of baseline + the causes' columns [dimensionless, chi-square scale]."""
        idx = np.concatenate([np.arange(self.n_base), *[self.cols[c] for c in causes]]).astype(int)
        iy = self.gram.shape[0] - 1
        g = self.gram[np.ix_(idx, idx)]
        b = self.gram[idx, iy]
        beta = gram_solve(g, b, self.n)
        return float(self.gram[iy, iy] - b @ beta)

    def test(self, chosen: list[str], cause: str) -> tuple[float, float]:
        """(D / disp, p-value with the look-elsewhere factor) for adding ``cause`` to ``chosen``."""
        d = (self.q(chosen) - self.q([*chosen, cause])) / self.disp
        k = max(int(self.cols[cause].size), 1)
        p = float(min(1.0, self.look_elsewhere.get(cause, 1.0) * stats.chi2.sf(max(d, 0.0), k)))
        return float(d), p


def search_factor(prob: Problem, cause: str) -> float:
    """How many independent choices a nonlinear search made (look-elsewhere factor)."""
    if cause == "periodic":
        span = 0.0
        for s in np.unique(prob.usable.session):
            t = prob.cols["t"][prob.usable.session == s]
            span += float(t.max() - t.min())
        return max(1.0, (0.45 * prob.rate_hz - F_MIN_HZ) * span)
    if cause == "warmup":
        return float(len(WARMUP_TAUS_S))
    return 1.0


def build_axis_lr(prob: Problem, cands: list[Candidate], axis: int) -> AxisLR:
    """Fit the error model on the largest model's residual and form the GLS Gram matrix."""
    regs = [c for c in cands if c.cause != "random_walk" and c.full.shape[1]]
    blocks = [prob.base, *[c.full for c in regs]]
    x = np.column_stack(blocks)
    y = prob.y[:, axis]
    beta, rank = lstsq(x, y)
    b0, _ = lstsq(prob.base, y)
    model = fit_noise(y - prob.base @ b0, prob.rate_hz)
    gls = StateSpaceGLS(model, prob.cols["t"], prob.usable.session)
    xy = np.column_stack([x, y])
    gram = gls.gram(xy)
    cols, k = {}, prob.base.shape[1]
    for c in regs:
        cols[c.cause] = np.arange(k, k + c.full.shape[1])
        k += c.full.shape[1]
    lr = AxisLR(gram, cols, prob.base.shape[1], prob.n, 1.0, model,
                {c.cause: search_factor(prob, c.cause) for c in regs})
    q_all = lr.q([c.cause for c in regs])
    lr.disp = max(1.0, q_all / max(prob.n - rank, 1))
    return lr


def heldout_walk(prob: Problem, model: NoiseModel, axis: int, chosen: list[Candidate]) -> np.ndarray:
    """Held-out residual (M,) of baseline + chosen causes + the slow states (a Kalman smoother).

    Per fold, the coefficients are fitted by GLS on the training rows and the slow states (walk,
    flicker bank) are smoothed from the training rows' residual; a held-out row is predicted by both.
    """
    y = prob.y[:, axis]
    out = np.empty_like(y)
    for k in range(prob.n_folds):
        test = prob.fold == k
        if not test.any():
            continue
        x = np.column_stack([prob.base, *[c.folds[k] for c in chosen if c.cause != "random_walk"]])
        gls = StateSpaceGLS(model, prob.cols["t"], prob.usable.session, (~test).astype(float))
        g = gls.gram(np.column_stack([x, y]))
        beta = gram_solve(g[:-1, :-1], g[:-1, -1], int((~test).sum()))
        r = y - x @ beta
        out[test] = (r - gls.smooth(r))[test]
    return out


def smooth_full(prob: Problem, model: NoiseModel, axis: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GLS fit of y on x (M, P) on all rows: (coefficients, slow-state estimate (M,) [deg/s])."""
    y = prob.y[:, axis]
    gls = StateSpaceGLS(model, prob.cols["t"], prob.usable.session)
    g = gls.gram(np.column_stack([x, y]))
    beta = gram_solve(g[:-1, :-1], g[:-1, -1], prob.n)
    return beta, gls.smooth(y - x @ beta)
