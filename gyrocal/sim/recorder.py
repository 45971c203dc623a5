"""Record what the virtual unit sent, incrementally, in the Contract 1 log format.

``LOG.csv`` holds what a host would have measured: t [s], wx wy wz [deg/s] (compensated output, as
sent), ax ay az [g], temp [degC], session (the boot counter) and ref_wx.. [deg/s] (the rotation
rate, as a turntable would report it). ``LOG.truth.csv`` holds the truth row by row beside it: t,
session, drift_w* (the systematic drift plus random walk in the raw output [deg/s]), comp_w* (what
the applied set subtracted [deg/s]), ref_w* [deg/s], g* [g], still (1 at rest).

Rows are buffered up to ``flush_rows`` and appended, so memory stays bounded however long it runs.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TextIO

import numpy as np

from gyrocal.logformat import CANONICAL_UNITS

LOG_COLUMNS = ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session", "ref_wx", "ref_wy", "ref_wz")
TRUTH_COLUMNS = ("t", "session", "drift_wx", "drift_wy", "drift_wz", "comp_wx", "comp_wy", "comp_wz",
                 "ref_wx", "ref_wy", "ref_wz", "gx", "gy", "gz", "still")


def truth_path_for(log_path: str | Path) -> Path:
    """``run.csv`` -> ``run.truth.csv``."""
    p = Path(log_path)
    return p.with_name(p.stem + ".truth" + (p.suffix or ".csv"))


class Recorder:
    """Appends chunks of unit output to ``path`` and the truth to ``truth_path_for(path)``."""

    def __init__(self, path: str | Path, metadata: Mapping[str, object] | None = None,
                 flush_rows: int = 4000) -> None:
        self.path = Path(path)
        self.truth_path = truth_path_for(path)
        self.flush_rows = flush_rows
        self.rows = 0
        self._pending: list[dict[str, np.ndarray]] = []
        self._pending_rows = 0
        self._log = self._open(self.path, metadata, LOG_COLUMNS)
        self._truth = self._open(self.truth_path, metadata, TRUTH_COLUMNS)

    @staticmethod
    def _open(path: Path, metadata: Mapping[str, object] | None, columns: tuple[str, ...]) -> TextIO:
        fh = path.open("w", encoding="utf-8", newline="")
        # the units line every Contract 1 writer gives (docs/logformat.md), as write_log does
        meta = {**{k: v for k, v in (metadata or {}).items() if k != "units"}, "units": CANONICAL_UNITS}
        for key, value in meta.items():
            fh.write(f"# {key}: {value}\n")
        fh.write(",".join(columns) + "\n")
        return fh

    def write(self, columns: Mapping[str, np.ndarray]) -> None:
        """Queue one chunk (a dict of equal-length arrays holding every column named above)."""
        n = len(columns["t"])
        if n == 0:
            return
        self._pending.append(dict(columns))
        self._pending_rows += n
        if self._pending_rows >= self.flush_rows:
            self.flush()

    def flush(self) -> None:
        if not self._pending:
            return
        merged = {k: np.concatenate([c[k] for c in self._pending]) for k in self._pending[0]}
        for fh, names in ((self._log, LOG_COLUMNS), (self._truth, TRUTH_COLUMNS)):
            data = np.column_stack([np.asarray(merged[c], dtype=np.float64) for c in names])
            np.savetxt(fh, data, delimiter=",", fmt="%.10g")
            fh.flush()
        self.rows += self._pending_rows
        self._pending, self._pending_rows = [], 0

    def close(self) -> None:
        if self._log.closed:
            return
        self.flush()
        self._log.close()
        self._truth.close()
