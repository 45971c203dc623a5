"""Offline still detection: which samples of a recorded log were taken with the unit at rest.

Shared by `gyrocal fit` (model/prep.py) and `gyrocal analyze` (analysis/segments.py), so a log's
still periods are the same whichever command reads it. The daemon decides on line, with half a window
of look-ahead, in daemon/stillness.py.

The detector looks at the gyro first (the accelerometer alone lets slow hand motion in, as the
mikoff data shows) and at the accelerometer second (a constant-rate turn has a small gyro variance
but a turning gravity vector). Thresholds are relative to the log's own quiet level, so the same rule
works for a 0.002 deg/s fibre gyro and a 0.3 deg/s MEMS part. Units: gyro deg/s, accel g, time s.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

AXES = ("x", "y", "z")
QUIET_QUANTILE = 0.1
"""The quiet level is this quantile of the rolling std: still for at least this share of the log."""


def sample_rate_hz(t: np.ndarray, session: np.ndarray) -> float:
    """The mean sample rate [Hz] within sessions: samples per second of recording.

    The mean, not the median interval, because some loggers deliver samples in bursts (sunsided's
    time stamps alternate short and long intervals), where the median would overstate the rate.
    """
    same = session[1:] == session[:-1]
    dt = np.diff(t)[same]
    span = float(np.sum(dt))
    if span <= 0:
        return 1.0
    return float(dt.size / span)


def _rolling(x: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Centred rolling mean and std of x (N,) over w samples (edges use shorter windows)."""
    n = x.size
    cs = np.concatenate(([0.0], np.cumsum(x)))
    cs2 = np.concatenate(([0.0], np.cumsum(x * x)))
    i = np.arange(n)
    lo = np.clip(i - w // 2, 0, n)
    hi = np.clip(i + w - w // 2, 0, n)
    cnt = hi - lo
    mean = (cs[hi] - cs[lo]) / cnt
    var = np.maximum((cs2[hi] - cs2[lo]) / cnt - mean**2, 0.0)
    return mean, np.sqrt(var)


def detect_still(
    columns: Mapping[str, np.ndarray], rate_hz: float, window_s: float = 0.4, k_std: float = 4.0,
    margin_s: float = 0.1, min_run_s: float = 0.5,
) -> np.ndarray:
    """A still mask (N,) from the gyro and accelerometer columns.

    A sample is still when, in a window of ``window_s`` [s] around it, every gyro axis has a
    rolling std below ``k_std`` times its quiet level (the 10 % quantile of the rolling std, so a
    log that moves most of the time still has a true quiet level), the rolling gyro mean stays
    within a band around the still median (a constant-rate turn), and the accelerometer std stays
    below ``k_std`` times its quiet level (gravity turning). Stretches are then shrunk by ``margin_s`` [s] at
    each end and dropped when shorter than ``min_run_s`` [s].
    """
    n = len(columns["t"])
    w = max(3, int(round(window_s * rate_hz)))
    ok = np.ones(n, dtype=bool)
    for a in AXES:
        mean, std = _rolling(np.asarray(columns[f"w{a}"], dtype=float), w)
        quiet = max(float(np.quantile(std, QUIET_QUANTILE)), 1e-9)
        ok &= std < k_std * quiet
        centre = np.median(mean[std < k_std * quiet]) if np.any(std < k_std * quiet) else np.median(mean)
        # a turn of a few deg/s held for a while; the band is wide against any bias change
        ok &= np.abs(mean - centre) < max(8.0 * quiet, 0.5)
        _, astd = _rolling(np.asarray(columns[f"a{a}"], dtype=float), w)
        # floor the quiet level at the accel's quantum: a quantised still axis (CAN: 1 mg) has a
        # rolling std of exactly 0 in many windows, which would otherwise make nothing still
        floor = max(1e-6, 0.5 * _quantum(np.asarray(columns[f"a{a}"], dtype=float)))
        ok &= astd < k_std * max(float(np.quantile(astd, QUIET_QUANTILE)), floor)
    session = np.asarray(columns.get("session", np.zeros(n)))
    return _shrink(ok, session, int(round(margin_s * rate_hz)), int(round(min_run_s * rate_hz)))


def _quantum(x: np.ndarray) -> float:
    """The smallest step between distinct values (the quantisation LSB), from up to 200k samples."""
    steps = np.diff(np.unique(x[:200_000]))
    steps = steps[steps > 0]
    return float(steps.min()) if steps.size else 0.0


def _shrink(mask: np.ndarray, session: np.ndarray, margin: int, min_len: int) -> np.ndarray:
    """Shrink every true stretch by ``margin`` samples per end; drop those below ``min_len``."""
    out = np.zeros_like(mask)
    starts, ends = _stretches(mask, session)
    for s, e in zip(starts, ends, strict=True):
        s2, e2 = s + margin, e - margin
        if e2 - s2 >= max(min_len, 1):
            out[s2:e2] = True
    return out


def _stretches(mask: np.ndarray, session: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) indices of the true stretches of ``mask`` within sessions."""
    brk = np.concatenate(([True], session[1:] != session[:-1]))
    prev = np.concatenate(([False], mask[:-1])) & ~brk
    nxt_brk = np.concatenate((brk[1:], [True]))
    nxt = np.concatenate((mask[1:], [False])) & ~nxt_brk
    starts = np.flatnonzero(mask & ~prev)
    ends = np.flatnonzero(mask & ~nxt) + 1
    return starts, ends
