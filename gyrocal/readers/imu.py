"""Shared by the foreign-format readers: SI arrays of one IMU -> LogData in deg/s, g, degC, s."""

from __future__ import annotations

import numpy as np

from gyrocal.logformat import CANONICAL_UNITS, LogData
from gyrocal.readers.units import FACTORS


def si_imu_log(t_s: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, temp_c: np.ndarray | None,
               metadata: dict[str, str], source: str, dropped: dict[str, int] | None = None) -> LogData:
    """Convert rad/s and m/s^2 to deg/s and g, drop non-finite rows (counted), order by time.

    A temperature column that is entirely NaN (a sensor that does not report it) is left out rather
    than dropping every row; a partly-NaN one drops its NaN rows.
    """
    drop = dict(dropped or {})
    cols = {"t": np.asarray(t_s, dtype=np.float64)}
    g = np.asarray(gyro_rad_s, dtype=np.float64) * FACTORS["gyro"]["rad/s"]
    a = np.asarray(accel_m_s2, dtype=np.float64) * FACTORS["accel"]["m/s^2"]
    for k, ax in enumerate("xyz"):
        cols[f"w{ax}"], cols[f"a{ax}"] = g[:, k], a[:, k]
    if temp_c is not None and np.isfinite(temp_c).any():
        cols["temp"] = np.asarray(temp_c, dtype=np.float64)
    n = cols["t"].size
    ok = np.ones(n, dtype=bool)
    for v in cols.values():
        ok &= np.isfinite(v)
    if (~ok).any():
        drop["nonfinite"] = drop.get("nonfinite", 0) + int((~ok).sum())
    order = np.argsort(cols["t"][ok], kind="stable")
    out = {k: v[ok][order] for k, v in cols.items()}
    out["session"] = np.zeros(out["t"].size)
    meta = dict(metadata)
    meta["units"] = CANONICAL_UNITS
    return LogData(out, meta, [], source, {k: v for k, v in drop.items() if v},
                   data_rows=n + sum(v for k, v in drop.items() if k != "nonfinite"))
