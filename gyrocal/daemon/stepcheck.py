"""A step of the bias within the blocks a set is being learnt from, found before it is averaged in.

Why: the estimator weighs every sample since learning started alike. A unit whose x bias stepped by
60 deg/h 20 s into its first tumble (a shock) was left uncalibrated for 250 s ("converged, but
predicted drift left 14.2 deg/h", falling as the new bias outweighed the old), then given a set
that averaged the two biases: 5.3 deg/h left where an undisturbed switch-on leaves 0.3, the alarm
off, since that set's own validation residual held the step (in process; an outside re-check saw
the same on a road drive after a relearn: 68 deg/h left with `alarm: false`). The drift alarm
watches a set once one is held; nothing watched the data a set is learnt from.

The test is the generalised likelihood ratio for a jump of one axis's bias in the linear model the
estimator fits, over the still blocks' means (blocks.py: the model is linear in its terms, so a
block's means are all the fit needs): for each block boundary c, the step column s_c = 1[i >= c]
after projecting out the model's terms. With the blocks weighted by their samples n_i, the fit's
residual r (weighted) and Q an orthonormal basis of the weighted terms, the step estimate at c is

    delta_c = sum_{i>=c} w_i r_i / (sum_{i>=c} n_i - |sum_{i>=c} w_i Q_i|^2),   w_i = sqrt(n_i),

all reverse cumulative sums: O(blocks x terms) for every boundary at once.

A step is believed only when it is far beyond chance and beyond the blocks' own scatter:
- its z (the estimate over its standard error, the error from the blocks' scatter left once the step
  is fitted, so misfit and wander count as noise) is at least ``z_min``;
- it is larger than ``floor_dps`` (the drift alarm's floor) and ``scatter_ratio`` times the RMS of
  the block residuals left once it is fitted, on either side of it (the quarter largest left out
  where a side has 8 blocks or more: a slow turn taken for rest), so a wandering bias (an MEMS
  unit's flicker: a continuum of small steps) is not cut into restarts that would keep its first
  set from ever being pushed;
- it stands alone on its axis (``alone_ratio``);
- ``min_before`` blocks lie before it (1) and ``min_after`` after it (8). With 3 asked before it, a
  step 1-1.5 s into a warm switch-on at rest was not placed and was averaged in: x left 2.4-3.6 deg/h
  for good where 0.1 is usual (in process). One block before it cannot tell a step from a turn-on
  transient (session.py says so); learning starts again after either.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gyrocal.daemon.blocks import Block, kept_blocks


@dataclass(frozen=True)
class Step:
    """A step found: on ``axis`` (0..2), of ``dps`` [deg/s] (the new bias minus the old), ``z``
    standard errors, with ``before`` blocks before it and ``after`` after it, the first of which
    closed at unit time ``t_s`` [s]."""

    axis: int
    t_s: float
    dps: float
    z: float
    after: int
    before: int


SPAN_MIN = 1e-2
"""Directions of the terms that the blocks span less than this share of the constant's (a gravity
term over tilts of under about 0.6 deg) are not fitted: a vehicle settling 0.3 deg let 10 free
gravity coefficients fit 4 blocks exactly (198 deg/h between tilts 0.005 g apart: 40,000 deg/h per
g), and its settling was taken for a step."""


def _basis(x: np.ndarray, n: np.ndarray) -> np.ndarray:
    """An orthonormal basis (B, r) of the directions the weighted terms ``x`` (B, P) span (SPAN_MIN)."""
    u, sv, _ = np.linalg.svd(x, full_matrices=False)
    return u[:, :int(np.sum(sv > SPAN_MIN * np.sqrt(n.sum())))]


def _steps(q: np.ndarray, y: np.ndarray, n: np.ndarray, min_before: int,
           min_after: int) -> list[tuple[int, float, float]]:
    """Per axis, the best step beside the model of orthonormal basis ``q`` (B, r), of the weighted
    ``y`` (B, 3) with block samples ``n`` (B,): (first block after it, its size [deg/s], its z); z 0
    where no boundary is testable."""
    nb = len(n)
    w = np.sqrt(n)
    rank = q.shape[1]
    r = y - q @ (q.T @ y)
    ssr = np.sum(r**2, axis=0)
    dof = nb - rank - 1

    def tail(a: np.ndarray) -> np.ndarray:  # sums over i >= c, for every c
        return np.cumsum(a[::-1], axis=0)[::-1]

    cand = np.arange(min_before, nb - min_after + 1)
    den = (tail(n) - np.sum(tail(q * w[:, None]) ** 2, axis=1))[cand]
    num = tail(r * w[:, None])[cand]
    ok = den > 1e-9 * n.sum()
    out = []
    for axis in range(3):
        if dof < 2 or not ok.any():
            out.append((0, 0.0, 0.0))
            continue
        gain = np.where(ok, num[:, axis] ** 2 / np.where(ok, den, 1.0), -1.0)  # the fall of the SSR
        i = int(np.argmax(gain))
        delta = float(num[i, axis] / den[i])
        sigma2 = (float(ssr[axis]) - float(gain[i])) / dof
        z = abs(delta) / np.sqrt(sigma2 / float(den[i])) if sigma2 > 0 else 0.0
        out.append((int(cand[i]), delta, float(z)))
    return out


def _side_rms(e: np.ndarray) -> float:
    """RMS [deg/s] of one side's block residuals ``e``, the quarter largest left out from 8 blocks on:
    a side of fewer must hold its level in every block. Why per side: 3 of the 4 blocks before a
    vehicle's settling ended held the slow turn's rate (198 deg/h, too slow for the still rule), and
    a quarter trimmed over both sides left them all out: the settling was taken for a 189 deg/h step."""
    kept = kept_blocks(np.abs(e), 0.25) if e.size >= 8 else np.arange(e.size)
    return float(np.sqrt(np.mean(e[kept] ** 2)))


def find_step(blocks: list[Block], min_before: int = 1, min_after: int = 8, z_min: float = 8.0,
              floor_dps: float = 0.002,
              scatter_ratio: float = 4.0, alone_ratio: float = 3.0) -> Step | None:
    """The largest believable step of one axis's bias among ``blocks`` (oldest first), or None.

    ``alone_ratio``: the step's z must be this many times that of the best second step on its axis
    once it is fitted. A lone step leaves flat residuals on both sides; a walking bias leaves more
    steps of the same order wherever the first is put (restarts on every one of them would keep a
    walking unit's first set from ever being pushed)."""
    nb = len(blocks)
    if nb < min_before + min_after:
        return None
    n = np.array([b.n for b in blocks], dtype=float)
    w = np.sqrt(n)
    x = np.array([b.phi for b in blocks]) * w[:, None]
    y = np.array([b.raw_dps for b in blocks]) * w[:, None]
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        return None
    q = _basis(x, n)
    best: Step | None = None
    for axis, (c, delta, z) in enumerate(_steps(q, y, n, min_before, min_after)):
        if z < z_min or (best is not None and z <= best.z):
            continue
        q2, _ = np.linalg.qr(np.column_stack([q, np.where(np.arange(nb) >= c, w, 0.0)]))
        e = (y[:, axis] - q2 @ (q2.T @ y[:, axis])) / w  # the block residuals with the step [deg/s]
        scatter = max(_side_rms(e[:c]), _side_rms(e[c:]))
        if abs(delta) < max(floor_dps, scatter_ratio * scatter):
            continue
        second = _steps(q2, y, n, min_before, min_after)[axis][2]
        if z < alone_ratio * second:
            continue
        best = Step(axis, float(blocks[c].t_s), delta, float(z), nb - c, c)
    return best
