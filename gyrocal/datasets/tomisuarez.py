"""tomisuarez2's ImuCalibration MPU6050 logs (MIT) as Contract 1 logs.

Source format: a key,value preamble (``Fs,100`` ...), a header ``ax,ay,az,gx,gy,gz`` and raw counts.
Ranges: +-2 g is 16384 counts per g, +-250 deg/s is 131 counts per deg/s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gyrocal.datasets._common import data_dir, make_log, read_table
from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData

COUNTS_PER_G = 16384.0
COUNTS_PER_DPS = 131.0


def load_tomisuarez(path: str | Path | None = None) -> LogData:
    """Load one CSV (default imu_static_test.csv)."""
    p = Path(path) if path else data_dir("tomisuarez_mpu6050") / "imu_static_test.csv"
    if p.is_dir():
        p = p / "imu_static_test.csv"
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as err:
        raise LogFormatError(f"{p}: cannot read ({err.strerror})") from err
    head = next((i for i, ln in enumerate(lines) if ln.strip().lower().startswith("ax,")), None)
    if head is None:
        raise LogFormatError(f"{p}: no header line 'ax,ay,az,gx,gy,gz'")
    pre = dict(ln.split(",", 1) for ln in lines[:head] if "," in ln)
    fs = float(pre.get("Fs", "100"))
    tab = read_table(p, ",", skip=head + 1)
    t = np.arange(tab.shape[0]) / fs
    meta = {"dataset": "tomisuarez_mpu6050", "sensor": "MPU6050", "rate_hz": f"{fs:g}", "file": p.name}
    return make_log(t, tab[:, 3:6] / COUNTS_PER_DPS, tab[:, 0:3] / COUNTS_PER_G, str(p), meta)
