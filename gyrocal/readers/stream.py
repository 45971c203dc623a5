"""From a stream of unit messages (decoded CAN frames or serial bytes) to a log, and back.

A recording of the link holds what the unit sent: HELLO at each switch-on, SAMPLEs, and answers
such as COEFF_REPORT. ``messages_to_log`` makes the log columns from it: ``session`` counts
switch-ons (a HELLO with a new serial or boot count, or a sample counter that goes back), ``t`` is
the unit's time, and the first HELLO and COEFF_REPORT go into the metadata (the report whole:
``applied_coeffs_dps`` as JSON, so a converted CSV still says how its output was compensated).
The decoder's counters (CRC failures, garbage bytes, seq gaps, ...) are the reader's ``dropped``
accounting. Consecutive samples may also come as one SAMPLE_DTYPE block (``readers.canbulk``):
the same rows as its samples one by one.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from math import isfinite
from typing import Any

import numpy as np

from gyrocal.logformat import LogData
from gyrocal.model.terms import T_ORIGIN_KEY
from gyrocal.protocol.messages import CoeffReport, Hello, Sample, SampleConflict

FIELDS = ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session")
SEQ_BACK = 1000
"""A sample counter this far below the last one means the unit restarted (as the engine decides)."""


def messages_to_log(messages: Iterable[Any], source: str, stats: Mapping[str, int] | None = None,
                    extra_dropped: Mapping[str, int] | None = None) -> LogData:
    """Build LogData from unit messages in stream order (samples in deg/s, g, degC, s)."""
    rows: list[tuple[float, ...]] = []
    chunks: list[np.ndarray] = []
    meta: dict[str, str] = {T_ORIGIN_KEY: "switch_on"}  # t is the unit's time since switch-on
    session = -1
    unit: tuple[int, int] | None = None
    last_seq: int | None = None
    in_session = 0
    nonfinite = 0
    conflicting_first = 0
    for m in messages:
        if isinstance(m, np.ndarray):  # a bulk-decoded block: in-order seq, finite values
            if not m.size:
                continue
            if session < 0:
                session = 0
            elif last_seq is not None and int(m["seq"][0]) + SEQ_BACK < last_seq:
                session, in_session = session + 1, 0
            last_seq = int(m["seq"][-1])
            if rows:
                chunks.append(np.asarray(rows, dtype=np.float64))
                rows = []
            block = np.empty((m.size, len(FIELDS)), dtype=np.float64)
            for i, f in enumerate(FIELDS[:-1]):
                block[:, i] = m[f]
            block[:, -1] = session
            chunks.append(block)
            in_session += m.size
            continue
        if type(m) is Sample:
            if session < 0:
                session = 0
            elif last_seq is not None and m.seq + SEQ_BACK < last_seq:
                session, in_session = session + 1, 0
            last_seq = m.seq
            g, a = m.gyro_dps, m.accel_g
            row = (m.t_s, g[0], g[1], g[2], a[0], a[1], a[2], m.temp_c, float(session))
            if not all(map(isfinite, row)):  # math's: numpy's per row costs more than the rest
                nonfinite += 1
                continue
            rows.append(row)
            in_session += 1
            if len(rows) >= 65536:
                chunks.append(np.asarray(rows, dtype=np.float64))
                rows = []
        elif type(m) is SampleConflict:
            # the sample before came again with other values: neither copy is known to be the unit's
            # (a forged copy sent first was believed: an outside user's CAN log, x constant +273 deg/h
            # where the truth was -180); the decoder counted the second, this drops the first
            if rows:
                rows.pop()
                conflicting_first += 1
            elif chunks and chunks[-1].shape[0]:
                chunks[-1] = chunks[-1][:-1]
                conflicting_first += 1
        elif isinstance(m, Hello):
            if (m.serial, m.boot_count) != unit:
                if session < 0:
                    session = 0
                elif in_session:  # a switch-on after samples: a new session
                    session, in_session = session + 1, 0
                unit = (m.serial, m.boot_count)
                last_seq = None
            meta.setdefault("unit_serial", str(m.serial))
            meta.setdefault("firmware", m.fw_version)
            meta.setdefault("boot_count", str(m.boot_count))
            if m.rate_hz:
                meta.setdefault("rate_hz", str(m.rate_hz))
        elif isinstance(m, CoeffReport) and "applied_version" not in meta:
            meta["applied_version"] = str(m.version)
            meta["applied_terms_id"] = f"0x{m.terms_id:04x}"
            meta["applied_coeffs_dps"] = json.dumps([list(r) for r in m.coeffs_dps])
    if rows or not chunks:
        chunks.append(np.asarray(rows, dtype=np.float64).reshape(-1, len(FIELDS)))
    table = np.concatenate(chunks)
    if table.shape[0]:  # sessions numbered 0, 1, ... in order of appearance
        table[:, -1] = np.unique(table[:, -1], return_inverse=True)[1]
    columns = {f: table[:, i].copy() for i, f in enumerate(FIELDS)}
    dropped: dict[str, int] = {}
    if nonfinite:
        dropped["nonfinite"] = nonfinite
    if conflicting_first:
        dropped["conflicting_first"] = conflicting_first
    for k, v in (stats or {}).items():
        if k not in ("frames", "bytes", "foreign_frames") and v:
            dropped[k] = int(v)
    for k, v in (extra_dropped or {}).items():
        if v:
            dropped[k] = int(v)
    return LogData(columns, meta, [], source, dropped,
                   data_rows=int(table.shape[0]) + nonfinite + conflicting_first)
