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

Accelerometer sign: the files hold the gravity vector, not the specific force of Contract 1. The
recording with x pointing up reads acc_x -0.996 g, and the one with y pointing down acc_y +1.013 g
(an outside check noticed az -1.03 g on recordings whose README draws z up). The loader negates
acc_* so that the up axis reads +1 g, as every other reader gives it; the metadata says so. The
analysis' findings do not change (the fit's gravity terms change sign, and their products do not),
but a term set fitted on the converted log now holds for a unit that reports specific force.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gyrocal.analysis.timestamps import retime
from gyrocal.datasets._common import data_dir, make_log, read_table
from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData


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
            "accel_sign": "negated: the files hold the gravity vector (x up reads -1 g); here +1 g is up"}
    return make_log(tab[:, 0], tab[:, 4:7], -tab[:, 1:4], str(p), meta, temp=tab[:, 7], session=session)
