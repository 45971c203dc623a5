"""A broad resonance in the residual's spectrum: band-limited noise a bank of low-pass members cannot make.

Why: on the hand-turned MPU-9150 / MPU-6050 logs (mikoff imu0-4, tomisuarez 90_x_rot) the residual's
spectrum rises from about 3x its high-frequency floor near 1 Hz to 8-16x at 10-12 Hz and falls back
to the floor by 14 Hz (hand tremor, or the sensor's low-pass filter, seen through the still periods).
Every Gauss-Markov member's spectrum falls with frequency, so the fitted model cannot rise towards
10 Hz: its Allan deviation is 0.13-0.15 decades low at tau 0.04 s and up to 0.12 decades high at
0.3-0.6 s, where the measured curve falls faster than white noise past the bump. A second-order
(AR(2)) member centred on the bump, with the bump's width, has that shape; it joins the error model as
one more ``NoiseModel.lines`` entry (part of the colour, not in the test's model: it has no power at
the low frequencies the regression causes live at).
"""

from __future__ import annotations

import numpy as np

from gyrocal.analysis.baseline import Problem
from gyrocal.analysis.candidates import gridded, spectrum

SMOOTH_HZ = 1.0
"""Boxcar width [Hz] of the spectrum the bump is looked for in (narrow lines vanish into it)."""
RATIO = 2.0
"""The bump's smoothed peak must stand this many times above the spectrum both at half and at 1.5x
its frequency: a peak with flanks on both sides, which a low-pass (monotone) spectrum never has. White
noise smoothed over 1 Hz of a minutes-long log varies by a few per cent."""
MIN_HZ = 2.0
"""Lowest centre [Hz]; slower content belongs to the slow states and the periodic cause."""


def find_resonance(prob: Problem, resid: np.ndarray) -> list[tuple[tuple[float, float], ...]]:
    """Per axis, ((centre, half width) [Hz],) of a broad spectral bump of the residual (M, 3), or ().

    The centre and the half width are the mean and the SD of the smoothed power above the upper
    flank's level (the spectrum at 1.5x the peak frequency) between half and 1.5x the peak frequency.
    """
    grids = gridded(prob, resid, np.ones(prob.n, dtype=bool))
    if not grids:
        return [(), (), ()]
    f, p = spectrum(prob, grids)
    df = float(f[1] - f[0])
    w = max(1, int(round(SMOOTH_HZ / df)))
    sm = _boxcar(p, w)
    top = 0.45 * prob.rate_hz / 1.5
    band = np.flatnonzero((f >= MIN_HZ) & (f <= top))
    out: list[tuple[tuple[float, float], ...]] = []
    for k in range(resid.shape[1]):
        if band.size < 2 * w:  # a band under 2 smoothing widths cannot show a peak with flanks
            out.append(())
            continue
        j = int(band[np.argmax(sm[band, k])])
        fc = float(f[j])
        left = float(np.interp(fc / 2, f, sm[:, k]))
        right = float(np.interp(1.5 * fc, f, sm[:, k]))
        if min(left, right) <= 0 or sm[j, k] < RATIO * max(left, right):
            out.append(())
            continue
        win = (f >= fc / 2) & (f <= 1.5 * fc)
        ex = np.maximum(sm[win, k] - right, 0.0)
        c = float(np.sum(f[win] * ex) / np.sum(ex))
        hw = float(np.sqrt(np.sum((f[win] - c) ** 2 * ex) / np.sum(ex)))
        out.append(((round(c, 3), round(max(hw, df), 3)),))
    return out


def _boxcar(p: np.ndarray, w: int) -> np.ndarray:
    """Centred moving average of p (F, K) over w bins along axis 0, by cumulative sums (O(F), where
    np.convolve is O(F w): a 3-hour 100 Hz log has 2^19 bins and w = 10,000)."""
    c = np.vstack([np.zeros((1, p.shape[1])), np.cumsum(p, axis=0)])
    n = p.shape[0]
    lo = np.clip(np.arange(n) - w // 2, 0, n)
    hi = np.clip(np.arange(n) + (w - 1) // 2 + 1, 0, n)
    return (c[hi] - c[lo]) / w
