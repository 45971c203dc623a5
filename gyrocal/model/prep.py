"""From a log to fit data: gravity direction, still periods, term matrix.

Gravity terms. Seed 000 (section 3) uses the projections gx, gy, gz of the gravity vector on the
gyro axes. We take them as the unit vector a/|a| of the measured specific force [g], per sample:
- at rest the accelerometer reads gravity, and its direction does not depend on the
  accelerometer's own scale errors (the imu_tk gains are nominal, the norm is off by ~1 %);
- it makes the identity gx^2 + gy^2 + gz^2 = 1 exact, so the null space the estimator reports is
  the model's (rank 9 for seed 000's terms), not an artefact of accelerometer noise;
- the unit applying the pushed coefficients must use the same unit vector (INTERFACES.md).

Still periods. The gravity model is static, so by default only samples at rest are used:
a centred moving window of ``window_s`` gives the standard deviation of each gyro and accelerometer
axis; a sample is still when both summed deviations are below ``factor`` times their 10th
percentile over the log (a noise-floor estimate that needs no sensor-specific threshold), and
the still run is at least one window long. ``--all-samples`` skips this.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gyrocal.logformat import LogData
from gyrocal.model.terms import TermSpec, derived_columns


@dataclass
class FitData:
    """Term matrix phi (N, P) [term units], gyro y (N, 3) [deg/s], t (N,) [s], still segment id (N,)."""

    phi: np.ndarray
    y: np.ndarray
    t: np.ndarray
    segment: np.ndarray
    total_rows: int

    def segment_means(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-segment means of phi and y: the seed's input/output pairs (one per rest period)."""
        ids, inv = np.unique(self.segment, return_inverse=True)
        n = np.bincount(inv).astype(np.float64)
        phi = np.column_stack([np.bincount(inv, c) / n for c in self.phi.T])
        y = np.column_stack([np.bincount(inv, c) / n for c in self.y.T])
        return phi, y


def gravity_direction(accel_g: np.ndarray) -> np.ndarray:
    """Unit gravity vectors (N, 3) from specific force (N, 3) [g]; zero rows stay zero."""
    norm = np.linalg.norm(accel_g, axis=1)
    return accel_g / np.where(norm > 0, norm, 1.0)[:, None]


def block_terms(spec: TermSpec, columns: dict[str, np.ndarray]) -> np.ndarray:
    """Terms (N, P) of a block of samples for ``Estimator.update_many``, gravity as a unit vector.

    ``columns`` holds at least ``ax ay az`` [g] and whatever other atoms the spec uses (``temp``,
    ``t_on``, ``dtemp``, ...). The daemon calls this on each block it pops from the ring.
    """
    cols = dict(columns)
    g = gravity_direction(np.column_stack([np.asarray(cols[f"a{a}"], dtype=np.float64) for a in "xyz"]))
    cols.update({"gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]})
    return spec.design(cols)


def _moving_std(x: np.ndarray, w: int) -> np.ndarray:
    """Centred moving standard deviation over w samples, summed in quadrature over columns (N,)."""
    n = len(x)
    h = w // 2
    c1 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x - x.mean(axis=0), axis=0)])
    c2 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum((x - x.mean(axis=0)) ** 2, axis=0)])
    lo = np.clip(np.arange(n) - h, 0, n)
    hi = np.clip(np.arange(n) + h + 1, 0, n)
    k = (hi - lo)[:, None]
    var = (c2[hi] - c2[lo]) / k - ((c1[hi] - c1[lo]) / k) ** 2
    return np.sqrt(np.maximum(var, 0.0).sum(axis=1))


def still_mask(t: np.ndarray, gyro_dps: np.ndarray, accel_g: np.ndarray, window_s: float = 0.5,
               factor: float = 3.0) -> np.ndarray:
    """Boolean (N,) still flags from gyro (N, 3) [deg/s] and accel (N, 3) [g] (module docstring)."""
    n = len(t)
    if n < 3:
        return np.ones(n, dtype=bool)
    dt = float(np.median(np.diff(t))) or 0.01
    w = max(3, int(round(window_s / dt)))
    sg, sa = _moving_std(gyro_dps, w), _moving_std(accel_g, w)
    still = (sg <= factor * np.percentile(sg, 10)) & (sa <= factor * np.percentile(sa, 10))
    seg = segment_ids(still)
    counts = np.bincount(seg[still]) if still.any() else np.zeros(0, int)
    return still & (counts[np.where(still, seg, 0)] >= w if counts.size else still)


def segment_ids(mask: np.ndarray) -> np.ndarray:
    """Label runs of True in mask 0, 1, 2, ... (the label of a False sample is meaningless)."""
    starts = mask & ~np.concatenate(([False], mask[:-1]))
    return np.maximum(np.cumsum(starts) - 1, 0)


def prepare(log: LogData, spec: TermSpec, all_samples: bool = False, window_s: float = 0.5) -> FitData:
    """Terms, gyro and time of the samples to fit: still ones by default, every one with all_samples."""
    cols = derived_columns(log.columns)
    g = gravity_direction(log.accel_g)
    cols.update({"gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]})
    phi = spec.design(cols)
    y = log.gyro_dps
    if all_samples:
        mask = np.ones(len(log), dtype=bool)
    else:
        mask = np.zeros(len(log), dtype=bool)
        sess = log["session"]
        for s in np.unique(sess):  # per switch-on, so one session's motion never shapes another's floor
            idx = np.flatnonzero(sess == s)
            mask[idx] = still_mask(log["t"][idx], y[idx], log.accel_g[idx], window_s)
    seg = segment_ids(mask) if not all_samples else np.zeros(len(log), dtype=int)
    return FitData(phi[mask], y[mask], log["t"][mask], seg[mask], len(log))
