"""sunsided's sensor-fusion MPU6050 "unmoved" recordings (EUPL-1.2) as Contract 1 logs.

Source format: ``mpu6050_combined.csv`` per recording with t_s, acc_x_g.., gyr_x_dps.., temp_C.
The data stays under EUPL-1.2 in data/sunsided_mpu6050 (its own folder and license). Given the
dataset folder, every recording becomes one session (the same board switched on again, in another
orientation); given one recording's folder or CSV, that recording alone.

Time stamps: ``t_s`` is the logger's read time, not the sample time. The logger drains the sensor
FIFO in bursts (1-2 ms apart within a burst, 40-70 ms between bursts) while the MPU6050 sampled at
a steady ~99.3-100 Hz, so the read times scramble everything above about 2 Hz (issue 12). Each
recording is therefore re-timed to its sample clock: a straight line of t against the sample
index (``gyrocal.analysis.timestamps``), after sorting by t (the rows are already in order). The
metadata key ``retimed`` records the clock rate, the share of bursty intervals and the largest lag.

Accelerometer sign: the two sets were logged with different conventions, and Contract 1 wants the
specific force (the up axis reads +1 g). Set 2 (the ``unmoved-with-*`` folders) holds the gravity
vector: z up reads acc_z -1.034 g, x up acc_x -0.996 g, y down acc_y +1.013 g; the loader negates
acc_x, acc_y and acc_z. Set 1 (``set1-*``) holds the specific force with x flipped, as the dataset's
README for set 1 says: z up reads acc_z +1.037 g and x up acc_x -0.996 g; the loader negates acc_x
alone. The gyro x is not flipped there: its bias is +4.54 deg/s in both sets. (An earlier loader
negated every recording, so set 1's z-up recording read -1.04 g beside set 2's +1.03 g in the same
orientation: an outside check.) The metadata says what was done to each recording.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gyrocal.analysis.timestamps import retime
from gyrocal.datasets._common import data_dir, make_log, read_table
from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData

SET1_PREFIX = "set1-"
"""Folders of the dataset's set 1 (specific force, x flipped); the others are set 2 (gravity vector)."""


def accel_signs(folder: str) -> np.ndarray:
    """Per-axis factors (3,) that turn a recording's acc_* into specific force [g] (module docstring)."""
    return np.array([-1.0, 1.0, 1.0]) if folder.startswith(SET1_PREFIX) else np.array([-1.0, -1.0, -1.0])


def _one(p: Path) -> tuple[np.ndarray, dict]:
    tab = read_table(p, ",", skip=1)
    if tab.shape[1] != 8:
        raise LogFormatError(f"{p}: {tab.shape[1]} columns where mpu6050_combined.csv has 8")
    tab = tab[np.argsort(tab[:, 0], kind="stable")]
    cols, notes = retime({"t": tab[:, 0]})
    tab[:, 0] = cols["t"]
    return tab, (notes[0] if notes else {})


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
    parts = [_one(f) for f in files]
    tabs = [tb for tb, _ in parts]
    session = np.concatenate([np.full(len(tb), float(i)) for i, tb in enumerate(tabs)])
    tab = np.vstack(tabs)
    meta = {"dataset": "sunsided_mpu6050", "sensor": "MPU6050", "license": "EUPL-1.2",
            "recordings": ";".join(f"{i}={f.parent.name}" for i, f in enumerate(files)),
            "retimed": ";".join(f"{i}=rate {n['rate_hz']:g} Hz, {n['far_interval_share']:.0%} bursty "
                                f"intervals, lag <= {n['max_lag_s']:g} s"
                                for i, (_, n) in enumerate(parts) if n)
            or "no (time stamps regular)",
            "accel_sign": ";".join(f"{i}=" + ("acc_x negated (set 1: specific force, x flipped)"
                                              if f.parent.name.startswith(SET1_PREFIX)
                                              else "negated (set 2: the gravity vector)")
                                   for i, f in enumerate(files))}
    signs = np.vstack([np.tile(accel_signs(f.parent.name), (len(tb), 1))
                       for f, tb in zip(files, tabs, strict=True)])
    return make_log(tab[:, 0], tab[:, 4:7], signs * tab[:, 1:4], str(p), meta, temp=tab[:, 7],
                    session=session)
