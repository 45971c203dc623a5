"""A recording as the unit's message stream: ``("msg", message)`` and ``("samples", block)`` events.

Link recordings (python-can logs, serial byte captures) hold the unit's own messages: they go
through the live link's decoders, in order. Any other log (CSV, .ulg, .bin, .tlog, rosbag2) holds samples
only: each session becomes a HELLO (serial, firmware and boot count from the log's metadata when it
has them) followed by its samples, with ``seq`` counting from 0 at the switch-on as a unit's does;
the set the unit held comes from the ``applied_*`` metadata, else the unit held none. Its ``t`` is
sent as the unit time a unit sends, since the switch-on: the log's ``t`` less that of the session's
first sample (as the analysis takes ``t_on``), so a warm-up term means the same to the replayed unit,
the daemon and `gyrocal analyze`; unless the metadata says ``t_origin: switch_on`` (a converted link
recording), whose ``t`` is the unit's own.

Sample blocks are ``SAMPLE_DTYPE`` arrays (the ring's records, rx = 0) of at most ``BLOCK`` samples.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gyrocal.daemon.ring import SAMPLE_DTYPE
from gyrocal.errors import LogFormatError, ProtocolError
from gyrocal.logformat import LogData
from gyrocal.model.terms import from_switch_on
from gyrocal.protocol.messages import CoeffReport, Hello, Sample
from gyrocal.readers import ReadOptions, detect_kind, read_any

BLOCK = 4096
Event = tuple[str, Any]


def samples_to_block(samples: list[Sample]) -> np.ndarray:
    """SAMPLE_DTYPE records of Sample messages (rx = 0)."""
    out = np.zeros(len(samples), dtype=SAMPLE_DTYPE)
    if samples:
        out["seq"] = [s.seq for s in samples]
        a = np.array([(s.t_s, *s.gyro_dps, *s.accel_g, s.temp_c) for s in samples], dtype=np.float64)
        for i, c in enumerate(("t", "wx", "wy", "wz", "ax", "ay", "az", "temp")):
            out[c] = a[:, i]
    return out


@dataclass
class Recording:
    """What ``events()`` replays, plus what a unit would answer before the stream says it.

    ``first_hello`` / ``first_report``: the recording's first HELLO and COEFF_REPORT (found by a
    scan), so the replayed unit can answer HELLO_REQUEST and COEFF_READ the way the recorded unit
    would have, even when the recording only shows the answer later.
    """

    path: str
    kind: str
    first_hello: Hello | None = None
    first_report: CoeffReport | None = None
    log: LogData | None = None
    stream: Any = None  # a readers.csvstream.CsvStream: a CSV read block by block
    counts: dict[str, int] = field(default_factory=dict)
    _messages: Any = None

    @property
    def warnings(self) -> list[str]:
        """What the reader noticed (complete for a streamed CSV once ``events()`` has run)."""
        if self.log is not None:
            return list(self.log.warnings)
        return list(self.stream.warnings) if self.stream is not None else []

    def events(self) -> Iterator[Event]:
        if self.log is not None:
            yield from _log_events(self.log)
            return
        if self.stream is not None:
            yield from _stream_events(self.stream)
            return
        rec = self._messages()
        pending: list[Sample] = []
        for m in rec.messages():
            if isinstance(m, np.ndarray):  # a block decoded in bulk (readers.canbulk)
                if pending:
                    yield "samples", samples_to_block(pending)
                    pending = []
                for i in range(0, m.size, BLOCK):
                    yield "samples", m[i:i + BLOCK]
                continue
            if type(m) is Sample:
                pending.append(m)
                if len(pending) >= BLOCK:
                    yield "samples", samples_to_block(pending)
                    pending = []
                continue
            if pending:
                yield "samples", samples_to_block(pending)
                pending = []
            yield "msg", m
        if pending:
            yield "samples", samples_to_block(pending)
        self.counts.update({k: int(v) for k, v in rec.stats().items() if v})
        self.counts.update({k: int(v) for k, v in getattr(rec, "counts", {}).items() if v})

    def dropped(self) -> dict[str, int]:
        """What the decoders (or the reader) left out, by reason."""
        if self.log is not None:
            return dict(self.log.dropped)
        if self.stream is not None:
            return dict(self.stream.dropped)
        return {k: v for k, v in self.counts.items() if k not in ("frames", "bytes", "foreign_frames",
                                                                 "host_frames")}


def open_recording(path: str, kind: str | None = None, options: ReadOptions | None = None) -> Recording:
    """A Recording of ``path``: link recordings stream their messages; other logs are read whole."""
    kind = kind or detect_kind(path)
    options = options or ReadOptions()
    if kind == "can":
        from gyrocal.readers.canlog import CanRecording

        def make() -> Any:
            return CanRecording(path, options.dbc, node_id=options.instance)
    elif kind == "serial":
        from gyrocal.readers.serialcap import SerialRecording

        def make() -> Any:
            return SerialRecording(path)
    elif kind == "csv":  # block by block: a long log never sits in memory whole
        from gyrocal.readers import not_utf8
        from gyrocal.readers.csvstream import CsvStream

        if (bad := not_utf8(path)) is not None:  # streamed, it would fail mid-replay (rc36b H4)
            raise LogFormatError(bad)
        stream = CsvStream(path, options.columns or None, options.units or None)
        return Recording(path, kind, stream=stream, first_report=applied_from_metadata(stream.metadata, path))
    else:
        log = read_any(path, kind, options)
        return Recording(path, kind, log=log, first_report=applied_from_metadata(log.metadata, path))
    rec = Recording(path, kind, _messages=make)
    for m in make().messages():  # the scan: who the unit is and which set it holds
        if isinstance(m, Hello) and rec.first_hello is None:
            rec.first_hello = m
        elif isinstance(m, CoeffReport) and rec.first_report is None:
            rec.first_report = m
        if rec.first_hello is not None and rec.first_report is not None:
            break
    return rec


def applied_from_metadata(meta: dict[str, str], where: str) -> CoeffReport | None:
    """The set a logged unit held, from ``applied_version/_terms_id/_coeffs_dps`` metadata (the CAN
    and serial readers write them; a CSV converted from such a log keeps them). None when absent."""
    if "applied_coeffs_dps" not in meta:
        return None
    try:
        rows = json.loads(meta["applied_coeffs_dps"])
        return CoeffReport(int(meta.get("applied_version", "0")), int(meta.get("applied_terms_id", "0"), 0),
                           rows)
    except (ValueError, TypeError, ProtocolError) as err:
        raise LogFormatError(f"{where}: metadata 'applied_*' unreadable ({err}); fix or delete those "
                             "lines") from None


def _fw(text: str) -> str:
    return text if re.fullmatch(r"\d{1,3}\.\d{1,3}\.\d{1,3}", text or "") else "0.0.0"


def _hello(meta: dict[str, str], k: int, t: np.ndarray) -> Hello:
    """The HELLO of a sample log's k-th session (identity from the metadata when it has one)."""
    serial = int(meta["unit_serial"]) if meta.get("unit_serial", "").isdigit() else 0
    boot0 = int(meta["boot_count"]) if meta.get("boot_count", "").isdigit() else 0
    dt = float(np.median(np.diff(t))) if t.size > 2 else 0.0
    rate = 1.0 / dt if dt > 0 else 0.0
    return Hello(serial & 0xFFFFFFFF, _fw(meta.get("firmware", "")), (boot0 + k) & 0xFFFF,
                 int(min(round(rate), 65535)))


def _block(cols: dict[str, np.ndarray], i0: int, i1: int, seq0: int, t0: float) -> np.ndarray:
    """Samples i0..i1 as ring records; ``t0`` [s] is the log time of the session's first sample."""
    b = np.zeros(i1 - i0, dtype=SAMPLE_DTYPE)
    b["seq"] = np.arange(seq0, seq0 + i1 - i0)
    for c in ("wx", "wy", "wz", "ax", "ay", "az"):
        b[c] = cols[c][i0:i1]
    b["t"] = cols["t"][i0:i1] - t0
    b["temp"] = cols["temp"][i0:i1] if "temp" in cols else 25.0
    return b


def _stream_events(stream: Any) -> Iterator[Event]:
    """Events of a CSV read block by block: a HELLO where ``session`` changes, then its samples."""
    session: float | None = None
    k, seq, t0 = -1, 0, 0.0
    for cols in stream.blocks():
        s = cols["session"]
        cuts = np.flatnonzero(np.diff(s) != 0) + 1
        for i0, i1 in zip(np.concatenate(([0], cuts)), np.concatenate((cuts, [s.size])), strict=True):
            if i1 <= i0:
                continue
            if session is None or s[i0] != session:
                session, k, seq = float(s[i0]), k + 1, 0
                t0 = 0.0 if from_switch_on(stream.metadata) else float(cols["t"][i0])
                yield "msg", _hello(stream.metadata, k, cols["t"][i0:i1])
            for j0 in range(i0, i1, BLOCK):
                j1 = min(j0 + BLOCK, i1)
                yield "samples", _block(cols, j0, j1, seq, t0)
                seq += j1 - j0


def _log_events(log: LogData) -> Iterator[Event]:
    meta = log.metadata
    serial = int(meta["unit_serial"]) if meta.get("unit_serial", "").isdigit() else 0
    boot0 = int(meta["boot_count"]) if meta.get("boot_count", "").isdigit() else 0
    sess = log["session"]
    cuts = np.flatnonzero(np.diff(sess) != 0) + 1
    starts = np.concatenate(([0], cuts)) if len(log) else np.zeros(0, dtype=int)
    ends = np.concatenate((cuts, [len(log)])) if len(log) else np.zeros(0, dtype=int)
    cols = {c: log[c] for c in ("t", "wx", "wy", "wz", "ax", "ay", "az")}
    unit_time = from_switch_on(meta)  # a converted link capture: t is the unit's already
    if log.has("temp"):
        cols["temp"] = log["temp"]
    for k, (i0, i1) in enumerate(zip(starts, ends, strict=True)):
        t = log["t"][i0:i1]
        rate = 1.0 / float(np.median(np.diff(t))) if t.size > 2 and np.median(np.diff(t)) > 0 else 0.0
        yield "msg", Hello(serial & 0xFFFFFFFF, _fw(meta.get("firmware", "")), (boot0 + k) & 0xFFFF,
                           int(min(round(rate), 65535)))
        for j0 in range(i0, i1, BLOCK):
            j1 = min(j0 + BLOCK, i1)
            yield "samples", _block(cols, j0, j1, j0 - i0, 0.0 if unit_time else float(t[0]))
