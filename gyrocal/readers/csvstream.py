"""A CSV log read block by block, for ``gyrocal replay`` of logs too long to hold whole.

The same parsing as ``logformat.read_log`` (numpy's parser for plain rows, the line loop naming the
line and column of a bad value), the same unit conversion and NaN accounting, on ``BLOCK_ROWS``
rows at a time, so memory stays at one block however long the log. Time order is checked across
blocks per session. ``dropped`` and ``warnings`` are complete once ``blocks()`` has run.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

from gyrocal.errors import LogFormatError
from gyrocal.logformat import (
    CANONICAL_UNITS,
    LogData,
    _fast_body,
    _numeric_columns,
    _slow_body,
    check_session_column,
    read_header,
)
from gyrocal.readers.units import (
    convert_columns,
    declared_units,
    units_warnings,
)

BLOCK_ROWS = 1 << 16


class CsvStream:
    """``metadata`` after construction; ``blocks()`` yields column dicts (deg/s, g, degC, s, session)."""

    def __init__(self, path: str, rename: Mapping[str, str] | None = None,
                 units: Mapping[str, str] | None = None, block_rows: int = BLOCK_ROWS) -> None:
        self.path = path
        self.rename = dict(rename or {})
        self.block_rows = block_rows
        with self._open() as fh:
            self.metadata, _, _ = read_header(fh, path, self.rename or None)
        self.units = declared_units(self.metadata.get("units", ""), f"{path}: '# units:' line")
        self.units.update(units or {})
        if self.units:
            self.metadata["units"] = CANONICAL_UNITS
        self.dropped: dict[str, int] = {}
        self.warnings: list[str] = []
        self.rows = 0

    def _open(self):  # noqa: ANN202 - a text file
        try:
            return Path(self.path).open(newline="", encoding="utf-8-sig")
        except OSError as err:
            raise LogFormatError(f"{self.path}: cannot open the log ({err.strerror})") from err

    def blocks(self) -> Iterator[dict[str, np.ndarray]]:
        name = self.path
        prev: list[float] = []  # session and time of the last row read
        with self._open() as fh:
            _, header, lineno = read_header(fh, name, self.rename or None)
            width = len(header)
            keep: list[int] | None = None
            names: list[str] = []
            while True:
                lines = list(itertools.islice(fh, self.block_rows))
                if not lines:
                    return
                rest = "".join(lines)
                if keep is None:
                    keep, ignored = _numeric_columns(rest, header)
                    names = [header[i] for i in keep]
                    self.warnings.extend(f"{name}: column '{c}' is not numeric (first row: {v!r}); ignored"
                                         for c, v in ignored)
                table, skipped = _fast_body(rest, width, lineno, keep)
                if table is None:
                    table, skipped = _slow_body(rest, width, lineno, header, name, keep)
                lineno += len(lines)
                if skipped:
                    self.dropped["nonfinite"] = self.dropped.get("nonfinite", 0) + len(skipped)
                cols = {h: table[:, i].copy() for i, h in enumerate(names)}
                cols.setdefault("session", np.zeros(table.shape[0]))
                convert_columns(cols, self.units)
                self._check_order(cols, prev, lineno)
                if self.rows == 0 and table.shape[0]:
                    self.warnings.extend(units_warnings(LogData(cols, source=name), self.units))
                self.rows += table.shape[0]
                yield cols

    def _check_order(self, cols: dict[str, np.ndarray], prev: list[float], lineno: int) -> None:
        """As read_log: within a session, t never goes back (here also across the block boundary)."""
        t, s = cols["t"], cols["session"]
        if t.size == 0:
            return
        check_session_column(s, self.path)
        back = bool(np.any((s[1:] == s[:-1]) & (np.diff(t) < 0)))
        if prev and s[0] == prev[0] and t[0] < prev[1]:
            back = True
        if back:
            raise LogFormatError(f"{self.path}: column 't' goes backwards within one session before line "
                                 f"{lineno + 1}; sort the rows or start a new session number")
        prev[:] = [float(s[-1]), float(t[-1])]
