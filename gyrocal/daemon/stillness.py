"""On-line still detection: which samples were taken with the unit at rest.

Seed 000's model is a static one: gravity terms explain drift only while the unit rests. During a
rotation the gyro reads the true rate and the accelerometer sees centripetal terms, so those samples
must not reach the estimator. A sample is declared still when the gyro spread and the accelerometer
norm stay quiet over a window that reaches both before and after it. That needs half a window of
look-ahead, so decisions come out delayed by ``half`` samples; the detector keeps only that tail
between blocks (bounded memory).

Units: gyro deg/s, accel g.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class StillConfig:
    window: int = 200  # samples
    gyro_std_dps: float = 0.05
    accel_tol_g: float = 0.05


class StillDetector:
    """Feed blocks of samples; get back the samples now decided, with their still flags."""

    def __init__(self, cfg: StillConfig) -> None:
        self.cfg = cfg
        self.half = max(1, cfg.window // 2)
        self._tail: np.ndarray | None = None  # samples not yet decided (plus look-behind)
        self._behind = 0  # how many leading rows of _tail are look-behind only

    def reset(self) -> None:
        self._tail = None
        self._behind = 0

    def feed(self, block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return (decided samples, still mask). ``block`` is a SAMPLE_DTYPE structured array."""
        if block.size == 0:
            return block, np.zeros(0, dtype=bool)
        buf = block if self._tail is None else np.concatenate([self._tail, block])
        h = self.half
        n = buf.size
        n_decide = n - self._behind - h  # rows that now have h samples of look-ahead
        if n_decide <= 0:
            self._tail = buf
            return buf[:0], np.zeros(0, dtype=bool)
        quiet = self._quiet(buf)
        # sample i is still if every sample within +-h is quiet
        padded = np.concatenate([[0], np.cumsum(~quiet)])
        lo = np.clip(np.arange(n) - h, 0, n)
        hi = np.clip(np.arange(n) + h + 1, 0, n)
        still = (padded[hi] - padded[lo]) == 0
        first = self._behind
        decided = buf[first:first + n_decide]
        mask = still[first:first + n_decide]
        keep_from = max(0, first + n_decide - h)
        self._tail = buf[keep_from:]
        self._behind = first + n_decide - keep_from
        return decided, mask

    def _quiet(self, buf: np.ndarray) -> np.ndarray:
        """Per sample: the gyro is near its local mean and |a| is near 1 g."""
        w = np.column_stack([buf["wx"], buf["wy"], buf["wz"]])
        a = np.column_stack([buf["ax"], buf["ay"], buf["az"]])
        k = max(3, self.cfg.window // 4)
        kernel = np.ones(k) / k
        smooth = np.column_stack([np.convolve(w[:, i], kernel, mode="same") for i in range(3)])
        dev = np.linalg.norm(w - smooth, axis=1)
        rate = np.linalg.norm(smooth, axis=1)
        a_ok = np.abs(np.linalg.norm(a, axis=1) - 1.0) < self.cfg.accel_tol_g
        return (dev < 4 * self.cfg.gyro_std_dps) & (rate < 1.0) & a_ok
