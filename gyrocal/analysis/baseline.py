"""The problem the analysis solves and the baseline model: gravity-dependent drift plus white noise.

The baseline is the simulation's own model of a unit (seed 000 eq. 10): a bias that jumps at every
switch-on (one offset per session, the "1" term), the nine gravity terms, and white noise. It is
fitted by rank-aware least squares: columns are scaled to unit RMS and singular directions below a
relative tolerance are left undetermined (minimum-norm solution), because gx^2 + gy^2 + gz^2 = 1
makes the 10-term model rank 9 at best and single-orientation logs determine far less.

While still, gravity is taken as each still run's mean specific force [g]: the unit does not turn
within a run, so the per-sample accelerometer noise carries no information about the drift and
would only add noise regressors.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from gyrocal.analysis.segments import AXES, Usable
from gyrocal.model.terms import SEED000_TERMS, TermSpec

GRAVITY_TERMS: tuple[str, ...] = tuple(t for t in SEED000_TERMS if t != "1")
MAX_SEGMENT_ROWS = 2000


@dataclass
class Problem:
    """Used samples of one log, ready for fitting.

    ``cols`` holds every log column and the derived ``t_on`` [s] and ``dtemp`` [degC/s], restricted
    to the used samples (M,). ``y`` (M, 3) is the gyro output minus the reference rate [deg/s].
    ``block`` numbers contiguous time blocks (the unit of the significance test); ``fold`` assigns
    blocks round-robin to ``n_folds`` folds, so every held-out block has training neighbours.
    """

    cols: dict[str, np.ndarray]
    y: np.ndarray
    usable: Usable
    block: np.ndarray
    fold: np.ndarray
    n_folds: int
    block_s: float
    base: np.ndarray  # (M, P0) baseline design: session offsets + gravity terms

    @property
    def rate_hz(self) -> float:
        return self.usable.rate_hz

    @property
    def n(self) -> int:
        return int(self.y.shape[0])


def lstsq(x: np.ndarray, y: np.ndarray, rcond: float = 1e-6) -> tuple[np.ndarray, int]:
    """Rank-aware least squares: coefficients (P,) or (P, K) in physical units, and the rank.

    See ``gram_solve``; this forms the Gram matrix from the design x (N, P) and targets y.
    """
    beta, rank = gram_solve(x.T @ x, x.T @ y, x.shape[0], rcond, return_rank=True)
    return beta, rank


def gram_solve(g: np.ndarray, b: np.ndarray, n: int, rcond: float = 1e-6, return_rank: bool = False):
    """Solve the normal equations g beta = b (g = X'X, b = X'y) with rank awareness.

    Columns are scaled to unit RMS first (from diag(g) / n), so the tolerance means the same for
    g, degC and s. The solution is the pseudo-inverse one through the eigen-decomposition of the
    scaled Gram matrix: directions whose singular value is below ``rcond`` times the largest are
    left undetermined (minimum norm), e.g. the 1 + gx^2 + gy^2 + gz^2 direction. The Gram route
    costs one BLAS pass over the data, which matters for 30-minute logs cross-validated many times.
    """
    scale = np.sqrt(np.maximum(np.diag(g), 0.0) / max(n, 1))
    scale = np.where(scale > 1e-300, scale, 1.0)
    gs = g / np.outer(scale, scale)
    lam, vec = np.linalg.eigh(gs)
    keep = lam > (rcond**2) * max(float(lam[-1]), 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    bs = (b.T / scale).T
    beta = vec @ (inv[:, None] * (vec.T @ bs.reshape(len(lam), -1)))
    beta = (beta.reshape(b.shape).T / scale).T
    return (beta, int(keep.sum())) if return_rank else beta


def _run_mean(x: np.ndarray, run: np.ndarray) -> np.ndarray:
    """Replace each sample of x (M,) by the mean of its run."""
    sums = np.bincount(run, weights=x)
    counts = np.bincount(run)
    return (sums / np.maximum(counts, 1))[run]


def build_problem(
    columns: Mapping[str, np.ndarray], usable: Usable, n_folds: int = 5, n_blocks_target: int = 40,
) -> Problem:
    """Restrict the derived columns to the used samples and lay out blocks and folds.

    Blocks are cut on time since switch-on, about ``total_duration / n_blocks_target`` long
    (clamped to 2..30 s), so a held-out block is long against the noise and short against the
    slow effects the analysis looks for.
    """
    idx = usable.index
    cols = {k: np.asarray(v, dtype=float)[idx] for k, v in columns.items()}
    ref = np.zeros((idx.size, 3))
    if usable.with_reference:
        ref = np.column_stack([cols[f"ref_w{a}"] for a in AXES])
    y = np.column_stack([cols[f"w{a}"] for a in AXES]) - ref
    duration = idx.size / usable.rate_hz
    block_s = float(np.clip(duration / n_blocks_target, 2.0, 30.0))
    sessions = usable.session
    key = np.floor(cols["t_on"] / block_s)
    pairs = np.column_stack([sessions, key])
    _, block = np.unique(pairs, axis=0, return_inverse=True)
    block = block.ravel()
    fold = block % n_folds
    if not usable.with_reference:
        for a in AXES:  # pose gravity: run means of the specific force
            cols[f"a{a}"] = _run_mean(cols[f"a{a}"], usable.run)
    base = baseline_design(cols, sessions)
    return Problem(cols, y, usable, block, fold, n_folds, block_s, base)


def baseline_design(cols: Mapping[str, np.ndarray], session: np.ndarray) -> np.ndarray:
    """Session offsets (the per-switch-on "1") and the nine gravity terms, (M, S + 9)."""
    uniq = np.unique(session)
    onehot = (session[:, None] == uniq[None, :]).astype(float)
    grav = TermSpec.parse(GRAVITY_TERMS).design(cols)
    return np.column_stack([onehot, grav])


def noise_dps(y: np.ndarray, run: np.ndarray) -> np.ndarray:
    """White-noise level per axis [deg/s]: the RMS of first differences within runs / sqrt(2).

    Differences remove the slow drift. Outliers beyond 6 robust sigmas (a knock) are left out; the
    RMS itself is not a median because quantised MEMS output (steps of 0.06 deg/s) makes medians of
    differences jump between quantisation levels.
    """
    same = run[1:] == run[:-1]
    d = np.diff(y, axis=0)[same]
    if d.shape[0] < 3:
        return np.full(3, np.nan)
    robust = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    lim = 6.0 * np.maximum(robust, np.sqrt(np.mean(d**2, axis=0)) / 3.0)
    keep = np.abs(d) <= lim
    return np.sqrt(np.sum(np.where(keep, d**2, 0.0), axis=0) / np.maximum(keep.sum(axis=0), 1) / 2.0)


def residual_stats(prob: Problem, resid: np.ndarray) -> dict:
    """Residual mean and RMS per session and per still run (segment, x y z), and the spread of
    per-run means against white noise.

    ``run_mean_excess`` is var(run means) / mean(sigma^2 / n_run): about 1 when the runs differ
    only by white noise, far above 1 when the bias moves between runs in a way the model misses.
    """
    out: dict = {"sessions": [], "runs": {}}
    for s in np.unique(prob.usable.session):
        m = prob.usable.session == s
        out["sessions"].append({
            "session": int(s), "samples": int(m.sum()),
            "mean_dps": dict(zip(AXES, np.mean(resid[m], axis=0).round(7).tolist(), strict=True)),
            "rms_dps": dict(zip(AXES, np.sqrt(np.mean(resid[m] ** 2, axis=0)).round(7).tolist(),
                                strict=True)),
        })
    run = prob.usable.run
    counts = np.bincount(run)
    t = prob.cols["t"]
    first = np.searchsorted(run, np.arange(counts.size))
    means = np.column_stack([np.bincount(run, weights=resid[:, k]) for k in range(3)]) / counts[:, None]
    rms = np.sqrt(np.column_stack([np.bincount(run, weights=resid[:, k] ** 2) for k in range(3)])
                  / counts[:, None])
    out["segments"] = [  # one row per still run (segment), capped so a long log stays readable
        {"t_start_s": round(float(t[first[j]]), 3), "samples": int(counts[j]),
         "session": int(prob.usable.session[first[j]]),
         "mean_dps": [round(float(v), 7) for v in means[j]], "rms_dps": [round(float(v), 7) for v in rms[j]]}
        for j in range(min(counts.size, MAX_SEGMENT_ROWS))
    ]
    keep = counts >= 5
    sigma = noise_dps(resid, run)
    for k, a in enumerate(AXES):
        means = (np.bincount(run, weights=resid[:, k]) / np.maximum(counts, 1))[keep]
        expected = float(np.mean(sigma[k] ** 2 / counts[keep])) if keep.any() else np.nan
        excess = float(np.var(means) / expected) if keep.sum() > 1 and expected > 0 else np.nan
        out["runs"][a] = {"count": int(keep.sum()),
                          "mean_std_dps": float(np.std(means)) if keep.any() else np.nan,
                          "run_mean_excess": round(excess, 3) if np.isfinite(excess) else None}
    return out
