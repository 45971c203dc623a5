"""Held-out residuals, the tau-averaged RMS of Contract 2, and the significance rule.

Cross-validation: blocks of time are assigned round-robin to folds (``Problem.fold``). Each fold's
samples are predicted by a model fitted on the other folds, so every sample gets a held-out residual.

Significance rule (measured in benchmarks/bench_analyze.py): a candidate term group is significant on
an axis when, over the held-out time blocks, the per-block reduction of the mean squared
tau-averaged residual is positive by a one-sided t-test with p < ``ALPHA`` (Bonferroni over
candidates and axes from a family level of 1%), and it explains at least ``MIN_FRACTION`` of the
baseline held-out variance. Blocks, not samples, are the test's units, because slow residuals are
correlated within a block.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats

from gyrocal.analysis.baseline import Problem, lstsq

FAMILY_ALPHA = 0.01
N_TESTS = 6 * 3  # six causes, three axes
ALPHA = FAMILY_ALPHA / N_TESTS
MIN_FRACTION = 0.05

Designer = Callable[[np.ndarray], np.ndarray]
"""Given a training mask (M,), return the extra design columns (M, p) for all samples."""


def penalized_lstsq(x: np.ndarray, y: np.ndarray, blocks: list[np.ndarray],
                    penalties: list[np.ndarray | None]) -> np.ndarray:
    """Least squares on x = [baseline, *blocks] with penalty rows appended (``pen @ coef = 0``)."""
    rows = []
    p0 = x.shape[1] - sum(b.shape[1] for b in blocks)
    k = p0
    for b, pen in zip(blocks, penalties, strict=True):
        if pen is not None and pen.size:
            r = np.zeros((pen.shape[0], x.shape[1]))
            r[:, k : k + b.shape[1]] = pen
            rows.append(r)
        k += b.shape[1]
    if rows:
        x = np.vstack([x, *rows])
        y = np.concatenate([y, np.zeros(sum(r.shape[0] for r in rows))])
    beta, _ = lstsq(x, y)
    return beta


def heldout_residual(prob: Problem, axis: int, extras: list[list[np.ndarray]],
                     penalties: list[np.ndarray | None] | None = None) -> np.ndarray:
    """Held-out residual (M,) of baseline + extra columns on one axis.

    ``extras[k]`` holds the extra design blocks to use for fold k (chosen on its training data);
    ``penalties`` (one per block, or None) are smoothness rows for that block's coefficients.
    """
    r = np.empty(prob.n)
    y = prob.y[:, axis]
    for k in range(prob.n_folds):
        test = prob.fold == k
        if not test.any():
            continue
        x = np.column_stack([prob.base, *extras[k]]) if extras[k] else prob.base
        pens = penalties if penalties is not None else [None] * len(extras[k])
        beta = penalized_lstsq(x[~test], y[~test], extras[k], pens)
        r[test] = y[test] - x[test] @ beta
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
