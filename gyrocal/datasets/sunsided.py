"""sunsided's sensor-fusion MPU6050 "unmoved" recordings (EUPL-1.2) as Contract 1 logs.

Source format: ``mpu6050_combined.csv`` per recording with t_s, acc_x_g.., gyr_x_dps.., temp_C.
The data stays under EUPL-1.2 in data/sunsided_mpu6050 (its own folder and license). Given the
dataset folder, every recording becomes one session (the same board switched on again, in another
orientation); given one recording's folder or CSV, that recording alone. Time stamps are made
non-decreasing (the source's per-sensor clocks differ slightly) by sorting.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gyrocal.datasets._common import data_dir, make_log, read_table
from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData


def _one(p: Path) -> np.ndarray:
    tab = read_table(p, ",", skip=1)
    if tab.shape[1] != 8:
        raise LogFormatError(f"{p}: {tab.shape[1]} columns where mpu6050_combined.csv has 8")
    return tab[np.argsort(tab[:, 0], kind="stable")]


def load_sunsided(path: str | Path | None = None) -> LogData:
    """Load the whole dataset (one session per recording) or one recording."""
    p = Path(path) if path else data_dir("sunsided_mpu6050")
    if p.is_file():
        files = [p]
    elif (p / "mpu6050_combined.csv").exists():
        files = [p / "mpu6050_combined.csv"]
    else:
        files = sorted(p.glob("*/mpu6050_combined.csv"))
    if not files:
        raise LogFormatError(f"{p}: no mpu6050_combined.csv found")
    tabs = [_one(f) for f in files]
    session = np.concatenate([np.full(len(tb), float(i)) for i, tb in enumerate(tabs)])
    tab = np.vstack(tabs)
    meta = {"dataset": "sunsided_mpu6050", "sensor": "MPU6050", "license": "EUPL-1.2",
            "recordings": ";".join(f"{i}={f.parent.name}" for i, f in enumerate(files))}
    return make_log(tab[:, 0], tab[:, 4:7], tab[:, 1:4], str(p), meta, temp=tab[:, 7], session=session)
