"""Shared helpers of the dataset loaders: units and where the project's copy of the data lives."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData

STANDARD_GRAVITY_M_S2 = 9.80665
"""Converts m/s^2 to g [m/s^2 per g]."""


def data_dir(name: str) -> Path:
    """The project's copy ``data/NAME`` if present, else ../shared/data/NAME."""
    repo = Path(__file__).resolve().parents[2]
    own = repo / "data" / name
    return own if own.exists() else repo.parent / "shared" / "data" / name


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
