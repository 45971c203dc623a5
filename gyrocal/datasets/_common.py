"""Shared helpers of the dataset loaders: units and where the project's copy of the data lives."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gyrocal.errors import ConfigError, LogFormatError
from gyrocal.logformat import LogData

STANDARD_GRAVITY_M_S2 = 9.80665
"""Converts m/s^2 to g [m/s^2 per g]."""


def data_dir(name: str) -> Path:
    """The project's copy ``data/NAME`` in a source checkout, else $GYROCAL_DATA/NAME.

    The datasets (22 MB) are not in the wheel: an installed gyrocal needs SRC or $GYROCAL_DATA, and
    says so (ConfigError) instead of guessing a path outside the install."""
    candidates = [Path(__file__).resolve().parents[2] / "data" / name]
    if os.environ.get("GYROCAL_DATA"):
        candidates.insert(0, Path(os.environ["GYROCAL_DATA"]) / name)
    for c in candidates:
        if c.exists():
            return c
    raise ConfigError(f"dataset {name!r}: no copy found ({', '.join(map(str, candidates))}); the datasets "
                      "ship in the source checkout's data/ folder, not in the wheel; fix: pass SRC (the "
                      "dataset's file or folder) or set GYROCAL_DATA to a checkout's data/ folder")


def read_table(path: Path, delimiter: str | None, skip: int = 0) -> np.ndarray:
    """A numeric table; a bad file raises LogFormatError naming the file and the problem."""
    try:
        return np.loadtxt(path, delimiter=delimiter, skiprows=skip, ndmin=2)
    except (OSError, ValueError) as err:
        raise LogFormatError(f"{path}: cannot read the dataset file ({err})") from err


def make_log(t: np.ndarray, gyro_dps: np.ndarray, accel_g: np.ndarray, source: str,
             metadata: dict[str, str], **extra: np.ndarray) -> LogData:
    """A LogData from arrays in log units (t s, gyro deg/s, accel g, temp degC)."""
    cols = {"t": np.asarray(t, float)}
    for k, a in enumerate("xyz"):
        cols[f"w{a}"] = np.asarray(gyro_dps[:, k], float)
        cols[f"a{a}"] = np.asarray(accel_g[:, k], float)
    cols.update({k: np.asarray(v, float) for k, v in extra.items()})
    if "session" not in cols:
        cols["session"] = np.zeros(cols["t"].size)
    ok = np.all(np.isfinite(np.column_stack(list(cols.values()))), axis=1)
    return LogData({k: v[ok] for k, v in cols.items()}, metadata, [], source)
