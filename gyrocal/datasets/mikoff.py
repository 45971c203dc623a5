"""Mikov's imu-calib recordings (five MPU-9150 units, MIT) as Contract 1 logs.

Source format (data/mikoff_mpu9150/README.md): space-separated ax ay az [m/s^2] then wx wy wz
[rad/s], 100 Hz, no time column. Each ``imuN.log`` is a different unit, so each file is one log
(one session), never sessions of one unit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gyrocal.datasets._common import STANDARD_GRAVITY_M_S2, data_dir, make_log, read_table
from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData

RATE_HZ = 100.0


def load_mikoff(path: str | Path | None = None) -> LogData:
    """Load one ``imuN.log`` (default imu0.log); t is sample index / 100 Hz [s]."""
    p = Path(path) if path else data_dir("mikoff_mpu9150") / "imu0.log"
    if p.is_dir():
        p = p / "imu0.log"
    tab = read_table(p, None)
    if tab.shape[1] != 6:
        raise LogFormatError(f"{p}: {tab.shape[1]} columns where mikoff logs have 6 (ax ay az wx wy wz)")
    t = np.arange(tab.shape[0]) / RATE_HZ
    return make_log(t, np.degrees(tab[:, 3:6]), tab[:, 0:3] / STANDARD_GRAVITY_M_S2, str(p),
                    {"dataset": "mikoff_mpu9150", "sensor": "MPU-9150", "rate_hz": "100", "file": p.name})
