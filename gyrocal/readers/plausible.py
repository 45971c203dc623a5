"""Rows no sensor could have measured: dropped and counted before any command uses a log.

Why: the daemon drops such samples before its estimators (daemon/tempcheck.py; the wire cannot
carry a gyro rate beyond +-2147.483648 deg/s), but `gyrocal fit` and `gyrocal analyze` took a log's
rows as they were. An outside user's CAN log whose temperature sensor sent the protocol's "no
reading" (-327.68 degC) gave an x constant of +271 deg/h where the truth was -180, and a temperature
slope of 0.68 deg/h/degC where it was 14.4, with nothing counted; one temperature of 1e308 in a CSV
ended `analyze` in a LinAlgError traceback, and one rate of 1e300 deg/s made `fit` refuse the whole
log as having "no still period" (rc36b H1, H5, M4). The same rules as the daemon's:

- a gyro rate beyond ``GYRO_MAX_DPS`` on any axis, or a specific force beyond ``ACCEL_MAX_G``:
  ``out_of_range``;
- a temperature outside the daemon's -60..150 degC, or a spike from the last believable one (the
  daemon's TemperatureCheck, per session; a jump that persists is followed): ``implausible_temperature``.
  A missing temperature (NaN, where the log has no sensor) is not judged.

Units: deg/s, g, degC, s.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from gyrocal.daemon.tempcheck import TemperatureCheck
from gyrocal.logformat import LogData

GYRO_MAX_DPS = 2147.483648
"""The largest rate [deg/s] the protocol's i32 gyro field carries (docs/protocol.md, Scalings); no
calibration uses a turn that fast."""
REF_SAMPLES = 64
"""The first samples of a session whose median temperature is the spike rule's first reference."""
ACCEL_MAX_G = 1000.0
"""A specific force [g] beyond any IMU accelerometer's range (high-g shock parts stop at 200-500 g)."""


def within_range(cols: Mapping[str, np.ndarray] | np.ndarray) -> np.ndarray:
    """(N,) bool: no gyro rate beyond GYRO_MAX_DPS [deg/s] and no specific force beyond ACCEL_MAX_G
    [g] on any axis, of log columns or the daemon's sample rows (fields wx..az). A NaN is not judged
    here: every reader and the engine count it as nonfinite."""
    ok = np.ones(len(cols["wx"]), dtype=bool)
    with np.errstate(invalid="ignore"):
        for f in ("wx", "wy", "wz", "ax", "ay", "az"):
            ok &= ~(np.abs(cols[f]) > (GYRO_MAX_DPS if f[0] == "w" else ACCEL_MAX_G))
    return ok


def drop_implausible(log: LogData) -> LogData:
    """``log`` without the rows no sensor could give, counted in ``log.dropped`` by reason."""
    n = len(log)
    if n == 0:
        return log
    range_ok = within_range(log.columns)
    temp_ok = np.ones(n, dtype=bool)
    if log.has("temp"):
        temp = np.asarray(log["temp"], dtype=np.float64)
        t = np.asarray(log["t"], dtype=np.float64)
        sess = np.asarray(log["session"]) if log.has("session") else np.zeros(n)
        judged = range_ok & np.isfinite(temp) & np.isfinite(t)
        for s in np.unique(sess[judged]):
            idx = np.flatnonzero(judged & (sess == s))
            # the reference is where the session starts (the daemon's first block's median): a whole
            # session's median, mid-way through a warm-up, made its first samples "spikes"
            check = TemperatureCheck(ref_c=float(np.median(temp[idx[:REF_SAMPLES]])), ref_t=float(t[idx[0]]))
            temp_ok[idx] = check.keep(t[idx], temp[idx])
    keep = range_ok & temp_ok
    if keep.all():
        return log
    for reason, count in (("out_of_range", int((~range_ok).sum())),
                          ("implausible_temperature", int((range_ok & ~temp_ok).sum()))):
        if count:
            log.dropped[reason] = log.dropped.get(reason, 0) + count
    log.columns = {k: v[keep] if isinstance(v, np.ndarray) and v.shape[:1] == (n,) else v
                   for k, v in log.columns.items()}
    return log
