"""From a log to fit data: gravity direction, still periods, term matrix.

Gravity terms. Seed 000 (section 3) uses the projections gx, gy, gz of the gravity vector on the
gyro axes. We take them as the unit vector a/|a| of the measured specific force [g], per sample:
- at rest the accelerometer reads gravity, and its direction does not depend on the
  accelerometer's own scale errors (the imu_tk gains are nominal, the norm is off by ~1 %);
- it makes the identity gx^2 + gy^2 + gz^2 = 1 exact, so the null space the estimator reports is
  the model's (rank 9 for seed 000's terms), not an artefact of accelerometer noise;
- the unit applying the pushed coefficients must use the same unit vector (INTERFACES.md).

Still periods. The gravity model is static, so by default only samples at rest are used, as
model/still.py detects them (the same detector as `gyrocal analyze`'s). ``--all-samples`` skips this.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gyrocal.logformat import LogData
from gyrocal.model.still import detect_still, sample_rate_hz
from gyrocal.model.terms import TermSpec, derived_columns, from_switch_on


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


def still_mask(t: np.ndarray, gyro_dps: np.ndarray, accel_g: np.ndarray, window_s: float = 0.4) -> np.ndarray:
    """Boolean (N,) still flags of one session from gyro (N, 3) [deg/s] and accel (N, 3) [g]."""
    n = len(t)
    if n < 3:  # too short to judge: not still (1-2 rows were "fitted" as still, with numpy warnings)
        return np.zeros(n, dtype=bool)
    cols = {"t": np.asarray(t, dtype=np.float64)}
    for k, a in enumerate("xyz"):
        cols[f"w{a}"], cols[f"a{a}"] = gyro_dps[:, k], accel_g[:, k]
    return detect_still(cols, sample_rate_hz(cols["t"], np.zeros(n)), window_s=window_s)


def segment_ids(mask: np.ndarray) -> np.ndarray:
    """Label runs of True in mask 0, 1, 2, ... (the label of a False sample is meaningless)."""
    starts = mask & ~np.concatenate(([False], mask[:-1]))
    return np.maximum(np.cumsum(starts) - 1, 0)


def prepare(log: LogData, spec: TermSpec, all_samples: bool = False, window_s: float = 0.4,
            applied: tuple[list[str], np.ndarray] | None = None) -> FitData:
    """Terms, gyro and time of the samples to fit: still ones by default, every one with all_samples.

    ``applied``: (terms, coefficients (3, P) [deg/s]) of the set the logged unit held. Its output is
    compensated with it (docs/logformat.md, section 1), so that set is added back and the fit is of
    the drift itself: a whole set, as `gyrocal push --file` takes it."""
    cols = derived_columns(log.columns, t_from_switch_on=from_switch_on(log.metadata))
    g = gravity_direction(log.accel_g)
    cols.update({"gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]})
    phi = spec.design(cols)
    y = log.gyro_dps
    if applied is not None:
        names, coeffs = applied
        y = y + TermSpec.parse(names).design(cols) @ np.asarray(coeffs, dtype=np.float64).T
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
