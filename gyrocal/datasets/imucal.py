"""The imucal Ferraris example session (mad-lab-fau, MIT) as a Contract 1 log.

Source: ``example_ferraris_session.csv`` with n_samples, gyr_x..z [deg/s], acc_x..z [m/s^2] at
102.4 Hz; ``example_ferraris_session_list.json`` gives the sample ranges of the six still positions
and three rotations. The analysis detects still periods itself; the labels are kept in metadata.
"""

from __future__ import annotations

import json
from pathlib import Path

from gyrocal.datasets._common import STANDARD_GRAVITY_M_S2, data_dir, make_log, read_table
from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData

RATE_HZ = 102.4


def load_imucal(path: str | Path | None = None) -> LogData:
    """Load the Ferraris session CSV (or the folder holding it)."""
    p = Path(path) if path else data_dir("imucal")
    if p.is_dir():
        p = p / "example_ferraris_session.csv"
    tab = read_table(p, ",", skip=1)
    if tab.shape[1] != 7:
        raise LogFormatError(f"{p}: {tab.shape[1]} columns where the Ferraris session has 7")
    meta = {"dataset": "imucal", "sensor": "unknown (imucal example)", "rate_hz": "102.4"}
    labels = p.with_name("example_ferraris_session_list.json")
    if labels.exists():
        parts = json.loads(labels.read_text(encoding="utf-8"))
        meta["segments"] = ";".join(f"{k}={v['start']}-{v['end']}" for k, v in parts.items())
    return make_log(tab[:, 0] / RATE_HZ, tab[:, 1:4], tab[:, 4:7] / STANDARD_GRAVITY_M_S2, str(p), meta)
