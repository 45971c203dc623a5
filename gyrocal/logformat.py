"""The CSV log format shared by measured data and simulator recordings (docs/logformat.md).

A log is a CSV file with a header row, optionally preceded by ``# key: value`` metadata lines.
Columns and units:

- ``t`` [s], ``wx wy wz`` [deg/s], ``ax ay az`` [g]: required;
- ``temp`` [degC], ``session`` [switch-on index], ``ref_wx ref_wy ref_wz`` [deg/s]: optional;
- any other numeric column: an extra covariate.

A ``# units: gyro=deg/s accel=g temp=degC time=s`` line declares the units the file holds; the
reader converts other declared units (rad/s, m/s^2, ms, ...) to these, and ``write_log`` always
writes this line. ``read_log(path, rename=..., units=...)`` reads a CSV with other column names or
units (``gyrocal fit --columns/--units``).

Why a hand-written reader rather than ``numpy.genfromtxt``: a bad file must be rejected with the
line and the column named, and rows holding NaN/Inf must be reported and skipped, never silently
turned into numbers an estimator would believe.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gyrocal.errors import LogFormatError

REQUIRED = ("t", "wx", "wy", "wz", "ax", "ay", "az")
CANONICAL_UNITS = "gyro=deg/s accel=g temp=degC time=s"
"""The units every reader delivers and ``write_log`` declares."""
OPTIONAL = ("temp", "session", "ref_wx", "ref_wy", "ref_wz")
AXES = ("x", "y", "z")


@dataclass
class LogData:
    """A log held as one float64 numpy array per column.

    ``columns`` always holds the required columns and ``session`` (zeros when the file had none).
    ``skipped_rows`` lists the 1-based file line numbers of rows dropped for NaN/Inf values.
    ``dropped`` counts every row or record a reader left out, by reason (``nonfinite``, ``crc``,
    ``no_accel``, ...), so that each command can say what it did not use. ``warnings`` holds
    what the reader noticed but could not decide (e.g. data that looks like SI units).
    """

    columns: dict[str, np.ndarray]
    metadata: dict[str, str] = field(default_factory=dict)
    skipped_rows: list[int] = field(default_factory=list)
    source: str = ""
    dropped: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    data_rows: int = 0
    """Data rows or records the source held, before anything was dropped."""

    def __len__(self) -> int:
        return int(self.columns["t"].shape[0])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    def has(self, name: str) -> bool:
        return name in self.columns

    @property
    def gyro_dps(self) -> np.ndarray:
        """Gyro output, shape (N, 3), deg/s."""
        return np.column_stack([self.columns[f"w{a}"] for a in AXES])

    @property
    def accel_g(self) -> np.ndarray:
        """Specific force, shape (N, 3), g."""
        return np.column_stack([self.columns[f"a{a}"] for a in AXES])

    @property
    def extra_columns(self) -> list[str]:
        """Columns beyond the contract's named ones: candidate covariates for the analysis."""
        known = set(REQUIRED) | set(OPTIONAL)
        return [c for c in self.columns if c not in known]

    def select(self, mask: np.ndarray) -> LogData:
        """A new log holding only the rows where ``mask`` is true (metadata kept)."""
        return LogData(
            {k: v[mask] for k, v in self.columns.items()},
            dict(self.metadata),
            list(self.skipped_rows),
            self.source,
            dict(self.dropped),
            list(self.warnings),
            self.data_rows,
        )


_ALIASES = {
    "t": ("time", "timestamp", "time_s", "t_s", "sec", "seconds"),
    "w": ("gyro_{a}", "gyr_{a}", "gyro{a}", "gyr{a}", "g{a}", "omega_{a}", "rate_{a}", "w_{a}", "{a}_gyro",
          "angular_velocity_{a}", "angular_velocity.{a}", "gyr{A}", "Gyr{A}", "gyro_{A}"),
    "a": ("acc_{a}", "accel_{a}", "acc{a}", "accel{a}", "a_{a}", "{a}_acc", "{a}_accel",
          "linear_acceleration_{a}", "linear_acceleration.{a}", "acc{A}", "Acc{A}", "accel_{A}"),
}


def suggest_columns(missing: list[str], header: list[str]) -> str:
    """A ``--columns`` guess for the missing columns from common names (gyro_x, acc_x, time, ...)."""
    lower = {h.lower(): h for h in header}
    out = []
    for col in missing:
        if col == "t":
            names = _ALIASES["t"]
        else:
            kind, axis = col[0], col[1]
            names = tuple(n.format(a=axis, A=axis.upper()) for n in _ALIASES[kind])
        hit = next((lower[n.lower()] for n in names if n.lower() in lower), None)
        if hit is not None:
            out.append(f"{col}={hit}")
    return ",".join(out)


def _parse_float(text: str, path: str, line: int, column: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise LogFormatError(
            f"{path}:{line}: column '{column}' holds {text!r}, which is not a number; "
            "fix the value or remove the row"
        ) from None


def read_header(fh: Iterable[str], name: str, rename: Mapping[str, str] | None = None,
                ) -> tuple[dict[str, str], list[str], int]:
    """Read the ``#`` metadata and the header row of an open CSV log, leaving ``fh`` at the first
    data row; returns (metadata, header in our column names, the header's line number)."""
    metadata: dict[str, str] = {}
    lines = iter(enumerate(fh, start=1))
    header: list[str] | None = None
    header_line = 0
    for lineno, raw in lines:
        text = raw.strip()
        if not text:
            continue
        if text.startswith("#"):
            body = text[1:].strip()
            if body.count(",") >= 2 and ":" not in body:
                # a header row behind a '#' (EuRoC, TUM-VI: "#timestamp [ns],w_RS_S_x [rad s^-1],..."):
                # a metadata line always has its ':'. Taken as metadata, the first data row became the
                # header (a foreign-log audit)
                header = [h.strip() for h in next(csv.reader([body]))]
                header_line = lineno
                break
            if ":" in body:
                key, value = body.split(":", 1)
                metadata[key.strip()] = value.strip()
            continue
        header = [h.strip() for h in next(csv.reader([text]))]
        header_line = lineno
        break
    if header is None:
        raise LogFormatError(f"{name}: no header row; the first non-# line must name the columns")
    if rename:
        absent = [f"{ours}={theirs}" for ours, theirs in rename.items() if theirs not in header]
        if absent:
            raise LogFormatError(f"{name}:{header_line}: --columns {', '.join(absent)}: no such column "
                                 f"in the header ({', '.join(header)})")
        back = {theirs: ours for ours, theirs in rename.items()}
        header = [back.get(h, h) for h in header]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        hint = suggest_columns(missing, header)
        raise LogFormatError(
            f"{name}:{header_line}: required column(s) {', '.join(missing)} missing from the "
            f"header; a log needs {', '.join(REQUIRED)} (map other names with --columns"
            + (f", perhaps --columns {hint}" if hint else "") + "; see docs/logformat.md)"
        )
    if len(set(header)) != len(header):
        raise LogFormatError(f"{name}:{header_line}: a column name appears twice in the header")
    return metadata, header, header_line


def read_log(path: str | Path, rename: Mapping[str, str] | None = None,
             units: Mapping[str, str] | None = None) -> LogData:
    """Read a CSV log, rejecting a malformed file and skipping non-finite rows.

    Raises LogFormatError naming the line and the column for: a missing required column, a
    non-numeric value, a row with the wrong number of fields, or time going backwards within a
    session. Rows with NaN or Inf are listed in ``skipped_rows`` and left out.

    ``rename`` maps our column names to the file's (``{"wx": "gyro_x"}``); ``units`` maps a
    quantity (gyro, accel, temp, time) to the unit the file holds, overriding its ``# units:`` line.
    Values are converted to deg/s, g, degC and s (see gyrocal.readers.units).
    """
    p = Path(path)
    name = str(p)
    try:
        fh = p.open(newline="", encoding="utf-8-sig")
    except OSError as err:
        raise LogFormatError(f"{name}: cannot open the log ({err.strerror})") from err
    with fh:
        metadata, header, header_line = read_header(fh, name, rename)
        width = len(header)
        rest = fh.read()
    keep, ignored = _numeric_columns(rest, header)
    bad_counts = np.zeros(len(keep), dtype=np.int64)  # NaN/Inf per column in the rows dropped
    table, skipped = _fast_body(rest, width, header_line, keep, bad_counts)
    if table is None:  # comments, blank lines or a bad value: the slow path names the line and column
        table, skipped = _slow_body(rest, width, header_line, header, name, keep, bad_counts)
    header = [header[i] for i in keep]
    by_column = {h: int(k) for h, k in zip(header, bad_counts, strict=True) if k}
    n_rows = table.shape[0]
    columns = {h: table[:, i].copy() for i, h in enumerate(header)}
    if "session" not in columns:
        columns["session"] = np.zeros(table.shape[0])
    from gyrocal.readers.units import (
        convert_columns,
        declared_units,
        units_warnings,
    )

    declared = declared_units(metadata.get("units", ""), f"{name}: '# units:' line")
    declared.update(units or {})
    convert_columns(columns, declared)
    if declared:
        metadata["units"] = CANONICAL_UNITS
    _check_time_order(columns, name)
    log = LogData(columns, metadata, skipped, name, {"nonfinite": len(skipped)} if skipped else {},
                  data_rows=n_rows + len(skipped))
    log.warnings.extend(f"{name}: column '{c}' is not numeric (first row: {v!r}); ignored"
                        for c, v in ignored)
    if by_column:  # a NaN in one column drops the whole row: say which column cost the rows
        log.warnings.append(
            f"{name}: {len(skipped)} of {n_rows + len(skipped)} rows dropped for NaN/Inf, by column: "
            + ", ".join(f"{c} {k}" for c, k in by_column.items())
            + ("; an optional column (temp, ref_w*, ...) can be left out of the file, or filled"
               if set(by_column) - set(REQUIRED) else ""))
    log.warnings.extend(units_warnings(log, declared))
    return log


def _numeric_columns(rest: str, header: list[str]) -> tuple[list[int], list[tuple[str, str]]]:
    """Indices of the columns to read, and the extra columns left out as text (a foreign CSV's
    frame id or date), judged on the first data row. Named columns are always read, so a text
    value there is an error naming its line."""
    first = _first_data_line(rest)
    if first is None:
        return list(range(len(header))), []
    fields = first.split(",")
    if len(fields) != len(header):
        return list(range(len(header))), []
    named = set(REQUIRED) | set(OPTIONAL)
    ignored: list[tuple[str, str]] = []
    for h, f in zip(header, fields, strict=True):
        if h in named:
            continue
        try:
            float(f)
        except ValueError:
            ignored.append((h, f.strip()))
    skip = {h for h, _ in ignored}
    return [i for i, h in enumerate(header) if h not in skip], ignored


def _first_data_line(rest: str) -> str | None:
    """The first line of ``rest`` that is neither blank nor a comment, stripped, or None; found line by
    line, without a copy of the body (a 3-hour log's is 108 MB)."""
    pos = 0
    while pos < len(rest):
        end = rest.find("\n", pos)
        end = len(rest) if end < 0 else end
        line = rest[pos:end].strip()
        if line and not line.startswith("#"):
            return line
        pos = end + 1
    return None


def _fast_body(rest: str, width: int, header_line: int, keep: list[int],
               bad_counts: np.ndarray | None = None) -> tuple[np.ndarray | None, list[int]]:
    """numpy's C parser for a body of plain numeric rows (~10x the line-by-line loop), else None.
    ``bad_counts`` (len(keep),): incremented per column by the NaN/Inf values of the rows dropped.

    The body reaches the parser as UTF-8 bytes, read in chunks, with no stripped copy: as a text
    stream (io.StringIO holds 4 bytes a character) a 3-hour 100 Hz log (108 MB) cost 2.1 GB of peak
    memory, over the issue's 2 GB for the whole analysis (benchmarks/bench_analyze.py --long)."""
    lo, hi = 0, len(rest)  # the body without the blank lines around it
    while lo < hi and rest[lo] == "\n":
        lo += 1
    while hi > lo and rest[hi - 1] == "\n":
        hi -= 1
    if hi <= lo:
        return np.zeros((0, len(keep))), []
    if rest.find("#", lo, hi) >= 0 or rest.find("\n\n", lo, hi) >= 0 or rest.find("\r", lo, hi) >= 0:
        return None, []
    nl = rest.find("\n", lo, hi)
    first = rest[lo:hi if nl < 0 else nl]
    if first.count(",") != width - 1:
        return None, []
    try:
        table = np.loadtxt(io.BytesIO(rest.encode("utf-8")), delimiter=",", dtype=np.float64, ndmin=2,
                           usecols=keep if len(keep) != width else None, encoding="utf-8")
    except ValueError:
        return None, []
    if table.shape[1] != len(keep):
        return None, []
    bad = ~np.isfinite(table).all(axis=1)
    if not bad.any():
        return table, []
    if bad_counts is not None:
        bad_counts += (~np.isfinite(table[bad])).sum(axis=0)
    first = header_line + 1 + lo  # the file line of the first row
    return table[~bad], [int(first + i) for i in np.flatnonzero(bad)]


def _slow_body(rest: str, width: int, header_line: int, header: list[str], name: str,
               keep: list[int], bad_counts: np.ndarray | None = None) -> tuple[np.ndarray, list[int]]:
    rows: list[list[float]] = []
    skipped: list[int] = []
    for lineno, raw in enumerate(rest.splitlines(), start=header_line + 1):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.split(",")
        if len(fields) != width:
            raise LogFormatError(
                f"{name}:{lineno}: {len(fields)} fields where the header has {width}; "
                "every row needs one value per column"
            )
        values = [_parse_float(fields[i], name, lineno, header[i]) for i in keep]
        if not all(math.isfinite(v) for v in values):
            skipped.append(lineno)
            if bad_counts is not None:
                bad_counts += ~np.isfinite(values)
            continue
        rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, len(keep)), skipped


def check_session_column(s: np.ndarray, name: str) -> None:
    """``session`` is a switch-on index: a whole number >= 0 (1.5 and -1 were taken as sessions)."""
    bad = np.flatnonzero((s < 0) | (s != np.round(s)))
    if bad.size:
        raise LogFormatError(f"{name}: data row {int(bad[0]) + 1}: column 'session' is {float(s[bad[0]]):g}; "
                             "it is the switch-on index, a whole number 0, 1, 2, ... (docs/logformat.md)")


def _check_time_order(columns: Mapping[str, np.ndarray], name: str) -> None:
    t, s = columns["t"], columns["session"]
    check_session_column(s, name)
    same = s[1:] == s[:-1]
    back = np.flatnonzero(same & (np.diff(t) < 0))
    if back.size:
        i = int(back[0]) + 1
        raise LogFormatError(
            f"{name}: data row {i + 1}: column 't' goes backwards ({float(t[i - 1]):g} -> {float(t[i]):g} s) "
            "within one session; sort the rows or start a new session number"
        )
    for sess in np.unique(s):  # a repeated stamp is allowed (non-decreasing); a clock that never moves is not
        ts = t[s == sess]
        if ts.size > 1 and ts[-1] == ts[0]:
            raise LogFormatError(
                f"{name}: column 't' does not advance in session {sess:g}: all {ts.size} rows are at "
                f"{float(ts[0]):g} s; write each sample's own time [s] (a logger's time stamp or the "
                "sample index over the rate)"
            )


def write_log(
    path: str | Path,
    columns: Mapping[str, np.ndarray],
    metadata: Mapping[str, str] | None = None,
    order: Iterable[str] | None = None,
) -> None:
    """Write a log (docs/logformat.md). Columns are written in ``order`` (default: named ones first).

    The ``# units:`` line is always written, with the canonical units the columns must hold.
    """
    names = list(order) if order is not None else _default_order(columns)
    data = np.column_stack([np.asarray(columns[c], dtype=np.float64) for c in names])
    meta = {k: v for k, v in (metadata or {}).items() if k != "units"}
    meta["units"] = CANONICAL_UNITS
    with Path(path).open("w", encoding="utf-8", newline="") as fh:
        for key, value in meta.items():
            fh.write(f"# {key}: {value}\n")
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, data, delimiter=",", fmt=[_time_format(data[:, i]) if c == "t" else "%.10g"
                                                  for i, c in enumerate(names)])


def _time_format(t: np.ndarray) -> str:
    """The format that keeps ``t`` [s] to the microsecond: 10 significant digits lost everything
    below 1 s of a time counted from 1970 (a PX4 SITL .ulg, every ROS bag's header.stamp), so a
    250 Hz log was written as runs of equal times (a foreign-log audit)."""
    top = float(np.nanmax(np.abs(t))) if t.size and np.isfinite(t).any() else 0.0
    return f"%.{min(17, max(10, int(np.ceil(np.log10(top + 1.0))) + 6))}g"


def _default_order(columns: Mapping[str, np.ndarray]) -> list[str]:
    first = [c for c in (*REQUIRED, *OPTIONAL) if c in columns]
    return first + [c for c in columns if c not in first]
