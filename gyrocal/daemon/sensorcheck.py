"""The sensor check: a unit whose sensors report what no working sensor can, under a valid CRC.

Why: the wire format and the CRC cannot tell a failed sensor's values from good ones; only physics
can. An integrator's campaign (rc36a) with a unit written from docs/protocol.md found the daemon
learning from such values and pushing them, without a word:

- a gyro axis stuck at 2.0 deg/s with no noise: a 7,200 deg/h bias pushed, the record predicting
  0.00002 deg/h left; railed at full scale, every sample was dropped and status blamed the noise level;
- an accelerometer sent in m/s^2 (clipped at 3.2767 "g"), dead (0 g), or with one axis saturated:
  its gravity direction is wrong, so are the gravity terms learnt from it, and the unit was left
  7-20 deg/h off (a constant alone pushed), or made worse by bias stages after false drift alarms.

What is checked, and where:

- A gyro axis that shows no noise through a whole still window (one value, or a spread of its
  sample-to-sample differences below 1e-5 deg/s, which a unit's own compensation of a stuck sensor
  gives) is stuck or railed: a live gyro's noise spans many of its 1e-6 deg/s counts. The still rule
  leaves such windows out (model/still.py, ``flat_axes``), so nothing is learnt or monitored from
  them; this check says which axis and what it reads.
- A sample the still rule found at rest whose accelerometer magnitude is outside
  1 +- ``ACCEL_TOL_G`` g is refused as still here: specific force at rest is 1 g, and a cheap MEMS
  part's scale error (a few %) and bias (up to 0.1 g) stay well inside.

Either is a state (status ``sensor.fault``, the reason's first words), a count, and one WARNING when
it starts (and an INFO line when it ends), never an exit. Units: deg/s, g, s.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

log = logging.getLogger("gyrocal.sensor")

ACCEL_TOL_G = 0.25
"""How far [g] a still sample's accelerometer magnitude may be from 1 g."""
SAY_AGAIN_S = 60.0
"""A fault that ends and comes back within this many seconds [s] is said at INFO, not again at WARNING."""


@dataclass
class SensorCheck:
    """Counts and the present fault; ``judge`` takes each block the still detector decided."""

    accel_refused: int = 0
    accel_norm_g: float | None = None  # the last refused still sample's magnitude [g]
    flat_axes: str = ""  # gyro axes with no noise (stuck, railed) at the newest row judged
    flat_value_dps: dict[str, float] = field(default_factory=dict)
    fault: str | None = None
    _warned_at: dict[str, float] = field(default_factory=dict)

    def reset(self) -> None:
        """A new switch-on: what the unit's sensors said before no longer holds (counts are kept)."""
        self.flat_axes, self.flat_value_dps, self.accel_norm_g = "", {}, None
        self._set(None, "", 0.0)

    def judge(self, rows: np.ndarray, still: np.ndarray, detector: Any, now: float) -> np.ndarray:
        """The still mask with the samples of an implausible accelerometer taken out; updates the fault.
        ``rows``: the decided samples (fields ax, ay, az [g]); ``detector``: the daemon's StillDetector,
        whose core counts the rows a stuck gyro axis left out."""
        core = detector.core
        flat = np.asarray(core.flat_now, dtype=bool)
        self.flat_axes = "".join(a for a, f in zip("xyz", flat, strict=True) if f)
        self.flat_value_dps = {a: float(v) for a, v, f in zip("xyz", core.flat_value_dps, flat, strict=True)
                               if f}
        accel_bad = False
        if rows.size and still.any():
            norm = np.sqrt(rows["ax"] ** 2 + rows["ay"] ** 2 + rows["az"] ** 2)
            bad = still & ~(np.abs(norm - 1.0) <= ACCEL_TOL_G)
            if bad.any():
                self.accel_refused += int(bad.sum())
                self.accel_norm_g = float(norm[bad][-1])
                still = still & ~bad
            accel_bad = not still.any() and bad.any()  # this block's rests all refused
            if still.any():
                self.accel_norm_g = None
        elif self.accel_norm_g is not None:
            accel_bad = True  # no rest since the last refused one: the fault holds
        parts = []
        if self.flat_axes:
            reads = ", ".join(f"{a} {v:.6g} deg/s" for a, v in self.flat_value_dps.items())
            parts.append(f"gyro {self.flat_axes} shows no noise ({reads}): a stuck or railed sensor; "
                         "no sample of it is learnt or monitored")
        if accel_bad and self.accel_norm_g is not None:
            parts.append(f"the accelerometer reads {self.accel_norm_g:.3g} g at rest, not 1 g (dead, "
                         "saturated, or not in g): its gravity is not believed, nothing is learnt at rest")
        kind = ("gyro" if self.flat_axes else "") + ("accel" if accel_bad else "")
        self._set("; ".join(parts) or None, kind, now)
        return still

    def _set(self, fault: str | None, kind: str, now: float) -> None:
        if fault is not None and self.fault is None:
            again = now - self._warned_at.get(kind, -1e18) < SAY_AGAIN_S
            log.log(logging.INFO if again else logging.WARNING, "unit sensor fault: %s", fault)
            self._warned_at[kind] = now
        elif fault is None and self.fault is not None:
            log.info("unit sensor fault over: its samples are plausible again (%s)", self.fault)
        self.fault = fault

    def status(self, flat_rows: np.ndarray) -> dict[str, Any]:
        """For ``gyrocal status``: the present fault (None when none), and the counts since start
        (``flat_rows``: per gyro axis, the samples the still rule judged stuck, StreamingStill)."""
        return {"fault": self.fault, "accel_refused_at_rest": self.accel_refused,
                "accel_tolerance_g": ACCEL_TOL_G, "flat_gyro_axes": self.flat_axes or None,
                "flat_gyro_samples": dict(zip("xyz", (int(v) for v in flat_rows), strict=True))}
