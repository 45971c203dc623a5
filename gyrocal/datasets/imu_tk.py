"""The imu_tk Xsens MTi recording (Tedaldi et al., ICRA 2014) as a Contract 1 log.

Source format (../shared/data/PROVENANCE.md): ``xsens_gyro.mat`` and ``xsens_acc.mat`` are ASCII
despite the name, four columns each: t [s], then x, y, z in raw 16-bit counts around an offset of
32768. Nominal gains (imu_tk MATLAB port, calibrate.m): gyro 4778, 4758, 4766 counts per rad/s,
accelerometer 415, 413, 415 counts per m/s^2. Both files share the time stamps (100 Hz, 51,175 rows).

The gains are nominal, so the accelerometer norm is not exactly 1 g; the fit uses the gravity
direction a/|a| (model/prep.py), which does not depend on the gains.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData

OFFSET_COUNTS = 32768.0
GYRO_COUNTS_PER_RAD_S = (4778.0, 4758.0, 4766.0)
ACCEL_COUNTS_PER_M_S2 = (415.0, 413.0, 415.0)
STANDARD_GRAVITY_M_S2 = 9.80665


def default_dir() -> Path:
    """The project's copy data/imu_tk_xsens (or $GYROCAL_DATA's); _common.data_dir says what is missing."""
    from gyrocal.datasets._common import data_dir

    return data_dir("imu_tk_xsens")


def load_imu_tk(directory: str | Path | None = None) -> LogData:
    """Load the recording: t [s], wx wy wz [deg/s], ax ay az [g], session 0 (one switch-on)."""
    d = Path(directory) if directory is not None else default_dir()
    tables = {}
    for name in ("gyro", "acc"):
        path = d / f"xsens_{name}.mat"
        try:
            tables[name] = np.loadtxt(path, dtype=np.float64, ndmin=2)
        except (OSError, ValueError) as err:
            raise LogFormatError(f"{path}: cannot read the imu_tk table ({err})") from err
        if tables[name].shape[1] != 4:
            raise LogFormatError(f"{path}: {tables[name].shape[1]} columns where t, x, y, z (4) are expected")
    gyro, acc = tables["gyro"], tables["acc"]
    if gyro.shape != acc.shape or np.abs(gyro[:, 0] - acc[:, 0]).max() > 1e-6:
        raise LogFormatError(f"{d}: xsens_gyro.mat and xsens_acc.mat do not share their time stamps")
    cols = {"t": gyro[:, 0].copy()}
    for k, axis in enumerate("xyz"):
        cols[f"w{axis}"] = np.degrees((gyro[:, k + 1] - OFFSET_COUNTS) / GYRO_COUNTS_PER_RAD_S[k])
        cols[f"a{axis}"] = (acc[:, k + 1] - OFFSET_COUNTS) / ACCEL_COUNTS_PER_M_S2[k] / STANDARD_GRAVITY_M_S2
    cols["session"] = np.zeros(len(gyro))
    meta = {"source": "imu_tk bin/test_data xsens (BSD)", "sensor": "Xsens MTi", "rate_hz": "100"}
    return LogData(cols, meta, [], str(d))
