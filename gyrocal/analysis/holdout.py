"""Held-out residuals, the tau-averaged RMS of Contract 2, and the significance rule.

Cross-validation: blocks of time are assigned round-robin to folds (``Problem.fold``). Each fold's
samples are predicted by a model fitted on the other folds, so every sample gets a held-out residual.

Significance rule (measured in benchmarks/bench_analyze.py): a candidate term group is significant on
an axis when, over the held-out time blocks, the per-block reduction of the mean squared
tau-averaged residual is positive by a one-sided t-test with p < ``ALPHA`` (Bonferroni over
candidates and axes from a family level of 1%), and it explains at least ``MIN_FRACTION`` of the
held-out variance the model so far leaves and ``MIN_FRACTION_OF_BASELINE`` of the baseline's.
Blocks, not samples, are the test's units, because slow residuals are correlated within a block.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats

from gyrocal.analysis.baseline import Problem, gram_solve, lstsq

FAMILY_ALPHA = 0.01
N_TESTS = 6 * 3  # six causes, three axes
ALPHA = FAMILY_ALPHA / N_TESTS
MIN_FRACTION = 0.05
"""Least share of the variance left by the model so far that a new cause must explain."""
MIN_FRACTION_OF_BASELINE = 0.01
"""Least share of the baseline held-out variance a cause must explain to be reported at all."""

Designer = Callable[[np.ndarray], np.ndarray]
"""Given a training mask (M,), return the extra design columns (M, p) for all samples."""


def _penalty_rows(p_total: int, blocks: list[np.ndarray], penalties: list[np.ndarray | None]
                  ) -> np.ndarray | None:
    """The penalty rows (R, P) over the full coefficient vector [baseline, *blocks]."""
    rows, k = [], p_total - sum(b.shape[1] for b in blocks)
    for b, pen in zip(blocks, penalties, strict=True):
        if pen is not None and pen.size:
            r = np.zeros((pen.shape[0], p_total))
            r[:, k : k + b.shape[1]] = pen
            rows.append(r)
        k += b.shape[1]
    return np.vstack(rows) if rows else None


def penalized_lstsq(x: np.ndarray, y: np.ndarray, blocks: list[np.ndarray],
                    penalties: list[np.ndarray | None]) -> np.ndarray:
    """Least squares on x = [baseline, *blocks] with penalty rows appended (``pen @ coef = 0``)."""
    pen = _penalty_rows(x.shape[1], blocks, penalties)
    if pen is not None:
        x = np.vstack([x, pen])
        y = np.concatenate([y, np.zeros((pen.shape[0],) + y.shape[1:])])
    beta, _ = lstsq(x, y)
    return beta


def heldout_residual(prob: Problem, extras: list[list[np.ndarray]],
                     penalties: list[np.ndarray | None] | None = None) -> np.ndarray:
    """Held-out residual (M, 3) of baseline + extra columns, all axes at once.

    ``extras[k]`` holds the extra design blocks to use for fold k (chosen on its training data);
    ``penalties`` (one per block, or None) are smoothness rows for that block's coefficients.
    When the blocks are the same in every fold, the per-fold Gram matrices are summed from one
    pass over the data (training Gram = total - fold), the cost that dominates long logs.
    """
    r = np.empty_like(prob.y)
    same = all(len(e) == len(extras[0]) and all(a is b for a, b in zip(e, extras[0], strict=True))
               for e in extras)
    if same:
        x = np.column_stack([prob.base, *extras[0]]) if extras[0] else prob.base
        pen = _penalty_rows(x.shape[1], extras[0], penalties or [None] * len(extras[0]))
        grams = [(x[prob.fold == k].T @ x[prob.fold == k], x[prob.fold == k].T @ prob.y[prob.fold == k],
                  int(np.sum(prob.fold == k))) for k in range(prob.n_folds)]
        g_all = sum(g for g, _, _ in grams)
        b_all = sum(b for _, b, _ in grams)
        n_all = sum(n for _, _, n in grams)
        for k, (gk, bk, nk) in enumerate(grams):
            if nk == 0:
                continue
            g, b = g_all - gk, b_all - bk
            if pen is not None:
                g = g + pen.T @ pen
            beta = gram_solve(g, b, n_all - nk)
            test = prob.fold == k
            r[test] = prob.y[test] - x[test] @ beta
        return r
    for k in range(prob.n_folds):
        test = prob.fold == k
        if not test.any():
            continue
        x = np.column_stack([prob.base, *extras[k]]) if extras[k] else prob.base
        pens = penalties if penalties is not None else [None] * len(extras[k])
        beta = penalized_lstsq(x[~test], prob.y[~test], extras[k], pens)
        r[test] = prob.y[test] - x[test] @ beta
    return r


def moving_average(r: np.ndarray, run: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Moving average of r over ``window`` samples within runs; returns (values, start index).

    A run shorter than the window contributes its mean once, so short still periods still count.
    """
    w = max(int(window), 1)
    n = r.size
    cs = np.concatenate(([0.0], np.cumsum(r)))
    starts = np.arange(max(n - w + 1, 0))
    valid = run[starts] == run[starts + w - 1] if starts.size else np.zeros(0, dtype=bool)
    vals = (cs[starts + w] - cs[starts]) / w
    vals, starts = vals[valid], starts[valid]
    counts = np.bincount(run)
    short = np.flatnonzero(counts < w)
    if short.size:
        first = np.searchsorted(run, short)
        sums = np.bincount(run, weights=r)
        vals = np.concatenate((vals, sums[short] / counts[short]))
        starts = np.concatenate((starts, first))
    return vals, starts


def tau_window(prob: Problem, tau_s: float) -> int:
    return max(1, int(round(tau_s * prob.rate_hz)))


def rms_tau(prob: Problem, r: np.ndarray, tau_s: float) -> float:
    """RMS of the residual after a moving average over tau_s [s] (Contract 2 holdout_rms)."""
    vals, _ = moving_average(r, prob.usable.run, tau_window(prob, tau_s))
    return float(np.sqrt(np.mean(vals**2))) if vals.size else float("nan")


@dataclass
class Comparison:
    """Held-out comparison of two nested models on one axis."""

    reduction: float  # (MS_a - MS_b), mean square of tau-averaged held-out residual [(deg/s)^2]
    p_value: float
    t_stat: float
    blocks: int


def compare(prob: Problem, r_a: np.ndarray, r_b: np.ndarray, tau_s: float) -> Comparison:
    """Does model b predict held-out blocks better than model a? One-sided t-test over blocks."""
    w = tau_window(prob, tau_s)
    va, sa = moving_average(r_a, prob.usable.run, w)
    vb, _ = moving_average(r_b, prob.usable.run, w)
    blk = prob.block[sa]
    nb = int(prob.block.max()) + 1
    cnt = np.bincount(blk, minlength=nb)
    keep = cnt > 0
    d = (np.bincount(blk, weights=va**2 - vb**2, minlength=nb)[keep]) / cnt[keep]
    reduction = float(np.mean(va**2) - np.mean(vb**2))
    if d.size < 3 or np.std(d) == 0:
        return Comparison(reduction, 1.0, 0.0, int(d.size))
    t = float(np.mean(d) / (np.std(d, ddof=1) / np.sqrt(d.size)))
    p = float(stats.t.sf(t, d.size - 1))
    return Comparison(reduction, p, t, int(d.size))
