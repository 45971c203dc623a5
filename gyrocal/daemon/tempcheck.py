"""The temperature check: a sample whose temperature no sensor could read is dropped and counted.

Why: a temperature is a regressor of the drift model. One glitched value in 997 (327.67 degC, the
i16 field's ceiling, under a valid CRC and the right seq) raised the rank of a 14-term set, was
pushed as v1 with ``temp_range_c`` [20.28, 327.67], and left 4.69 deg/h at 35 degC where 0.47 was
expected (a serial integrator's unit). The wire format and the CRC cannot tell such a value; only
physics can: a sensor's temperature stays within ``TEMP_MIN_C``..``TEMP_MAX_C`` and moves slowly.

- Out of range: dropped.
- A step from the last accepted temperature of more than ``STEP_C`` plus ``RATE_C_PER_S`` times
  the time between them: dropped (a spike). ``RESYNC`` such samples in a row are a real jump (a
  sensor re-initialised, another unit): the check takes the new level from there.
- The reference is the block's median at the start, after a gap of ``GAP_S`` and at every switch-on
  (``reset``), so a glitch first in a block is not taken as the reference.

Units: degC, s. The samples are numpy structured rows with ``t`` and ``temp`` (daemon/ring.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TEMP_MIN_C = -60.0
"""Colder than any vehicle's IMU works [degC] (industrial parts are specified from -40 degC)."""
TEMP_MAX_C = 150.0
"""Hotter than any IMU works [degC] (automotive parts to 125 degC); 327.67 is the i16 field's ceiling."""
STEP_C = 1.0
"""A temperature step [degC] allowed between two samples whatever their interval (quantisation,
a 10 Hz temperature held between updates)."""
RATE_C_PER_S = 5.0
"""... plus this rate [degC/s] times their interval: faster than any IMU's case warms or cools."""
GAP_S = 5.0
"""No sample for this long [s]: the last temperature no longer says where the next one should be."""
RESYNC = 50
"""Steps in a row that are taken for a real jump, from which the check follows the new level."""


@dataclass
class TemperatureCheck:
    """Keeps the last accepted temperature [degC] and its time [s]; ``keep`` judges each block."""

    ref_c: float | None = None
    ref_t: float | None = None
    rejected_in_a_row: int = 0
    out_of_range: int = 0
    spikes: int = 0

    def reset(self) -> None:
        """A new switch-on: the unit may have cooled or warmed since."""
        self.ref_c = self.ref_t = None
        self.rejected_in_a_row = 0

    @property
    def dropped(self) -> int:
        return self.out_of_range + self.spikes

    def keep(self, t: np.ndarray, temp: np.ndarray) -> np.ndarray:
        """(N,) bool: the samples whose temperature is believable (times [s], temperatures [degC])."""
        ok = (temp >= TEMP_MIN_C) & (temp <= TEMP_MAX_C)
        self.out_of_range += int((~ok).sum())
        if not ok.any():
            return ok
        if self.ref_c is None or self.ref_t is None or t[ok][0] - self.ref_t > GAP_S:
            self.ref_c, self.ref_t = float(np.median(temp[ok])), float(t[ok][0])
        tt, vv = t[ok], temp[ok]
        prev_t = np.r_[self.ref_t, tt[:-1]]
        prev_v = np.r_[self.ref_c, vv[:-1]]
        if np.all(np.abs(vv - prev_v) <= STEP_C + RATE_C_PER_S * np.abs(tt - prev_t)):
            self.ref_c, self.ref_t = float(vv[-1]), float(tt[-1])  # the usual block: no step
            self.rejected_in_a_row = 0
            return ok
        idx = np.flatnonzero(ok)
        for i in idx:  # a step somewhere: judged against the last accepted sample, one by one
            limit = STEP_C + RATE_C_PER_S * abs(float(t[i]) - self.ref_t)
            if abs(float(temp[i]) - self.ref_c) <= limit or self.rejected_in_a_row >= RESYNC:
                self.ref_c, self.ref_t = float(temp[i]), float(t[i])
                self.rejected_in_a_row = 0
            else:
                ok[i] = False
                self.spikes += 1
                self.rejected_in_a_row += 1
        return ok
