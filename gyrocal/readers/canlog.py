"""Reader ``can``: python-can log files (.asc, .blf, candump .log, .trc, .mf4, ...) with our DBC.

``can.LogReader`` picks the file reader by extension, so every format python-can reads works here.
Frames go through the same ``CanDecoder`` as the live CAN link, and, as there, only frames the DBC
marks as sent by the UNIT are decoded: a bus recording also holds the host's COEFF_READ/WRITE
frames (counted as ``host_frames``, not dropped data). Error and remote frames are counted apart.

A .blf is read by our own batched reader (``readers.blf``) and decoded in bulk where the frames
are regular (``readers.canbulk``): the same samples and counters as ``can.LogReader`` and the
decoder frame by frame, 15 to 20 times faster (benchmarks/bench_replay.py). What that reader
does not believe (a damaged container, an object cut off) is counted in ``dropped`` as
``blf_<reason>``. A file that does not start with a BLF header goes to ``can.LogReader``, which
names what is wrong.
"""

from __future__ import annotations

import collections
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from gyrocal.errors import ConfigError, LogFormatError
from gyrocal.logformat import LogData
from gyrocal.readers import ReadOptions
from gyrocal.readers.stream import messages_to_log


def _partial_last_line(path: str) -> int:
    """Bytes of a text log's last line when it lacks its newline (cut mid-write), else 0."""
    try:
        with open(path, "rb") as fh:
            fh.seek(0, 2)
            size = fh.tell()
            fh.seek(max(0, size - 4096))
            tail = fh.read()
    except OSError:
        return 0
    if not tail or tail.endswith(b"\n") or b"\0" in tail:
        return 0
    last = tail[tail.rfind(b"\n") + 1:]
    if not last.strip() or last.strip().lower().startswith(b"end"):  # an .asc trailer, not a frame
        return 0
    return len(last)


class CanRecording:
    """The unit messages of a python-can log, in file order, with the decoder's counters after use."""

    def __init__(self, path: str, dbc: str | None = None, fast: bool = True, node_id: int = 0) -> None:
        import can

        from gyrocal.drivers.can_link import frame_ids_sent_by
        from gyrocal.protocol.can_codec import CanCodec

        if not Path(path).exists():
            raise LogFormatError(f"{path}: cannot open the log (no such file)")
        if not 0 <= node_id <= 15:
            raise ConfigError(f"--instance {node_id}: for a CAN log it is the unit's node id, 0..15 "
                              "(docs/protocol.md, section 3)")
        self.path = path
        self._can = can
        # the unit's node id (`--instance N`): a recording of a node-3 unit was unreadable, and a DBC
        # with its ids moved was refused (a foreign-log audit)
        self.codec = CanCodec(dbc, node_id=node_id)
        self.decoder = self.codec.decoder()
        self.accept = frame_ids_sent_by(self.codec, "UNIT")
        self.host_ids = frame_ids_sent_by(self.codec, "HOST")
        """The host's frames to this node: counted as host_frames; other nodes' are foreign."""
        self.counts = {"host_frames": 0, "error_frames": 0}
        self.fast = fast and path.lower().endswith(".blf")
        """Read a .blf with readers.blf and decode it in bulk (False: can.LogReader, frame by frame)."""
        self.bulk_samples = 0

    def route(self, frame: Any) -> Iterator[Any]:
        """One frame of the recording: error and host frames counted, the rest fed to the decoder."""
        accept, counts = self.accept, self.counts
        if frame.is_error_frame:
            counts["error_frames"] += 1
        elif accept is not None and frame.arbitration_id in accept:
            yield from self.decoder.feed(frame)
        elif not frame.is_extended_id and (frame.arbitration_id in self.host_ids if self.host_ids is not None
                                           else accept is not None and frame.arbitration_id >> 8 == 1):
            counts["host_frames"] += 1
        else:
            yield from self.decoder.feed(frame)  # the decoder counts foreign frames itself

    def messages(self) -> Iterator[Any]:
        """Decoded unit messages (Sample, Hello, CoeffReport, ...) in the order of the file; a .blf
        read in bulk also yields SAMPLE_DTYPE blocks (rx = 0) of consecutive samples."""
        if self.fast:
            from gyrocal.readers.blf import BlfReader

            try:
                blf = BlfReader(self.path)
            except LogFormatError:
                blf = None  # not a BLF header: python-can's reader says what it is
            if blf is not None:
                from gyrocal.readers.canbulk import BulkCanDecoder

                bulk = BulkCanDecoder(self.codec, self.decoder, self.accept, self.route, self.counts,
                                      self.host_ids)
                for frames in blf.chunks():
                    yield from bulk.messages(frames)
                for reason, n in blf.dropped.items():
                    self.counts[f"blf_{reason}"] = n
                self.bulk_samples = bulk.bulk_samples
                return
        try:
            reader = self._can.LogReader(self.path)
        except Exception as err:  # unknown suffix, unreadable file, BLFParseError, ...
            raise LogFormatError(f"{self.path}: python-can cannot read it ({err})") from err
        route = self.route
        try:
            for frame in reader:
                yield from route(frame)
            cut = _partial_last_line(self.path)
            if cut:  # a cut last line that python-can skipped, or read as a short frame: said all the same
                self.counts["truncated_bytes"] = cut
        except Exception as err:  # python-can's readers raise their own errors on a damaged file
            if isinstance(err, LogFormatError):
                raise
            cut = _partial_last_line(self.path)
            if cut:
                # a text log whose last line was cut (a logger killed mid-write): the frames before it
                # stand and the cut bytes are counted, as the .cap and .blf readers do (it refused the
                # whole file: a foreign-log audit)
                self.counts["truncated_bytes"] = cut
                return
            raise LogFormatError(f"{self.path}: python-can failed while reading it ({err})") from err
        finally:
            stop = getattr(reader, "stop", None)
            if stop is not None:
                stop()

    def stats(self) -> dict[str, int]:
        return self.decoder.stats.as_dict()


def read_canlog(path: str, options: ReadOptions, fast: bool = True) -> LogData:
    """A python-can log's SAMPLEs as log columns; HELLOs split sessions. ``fast=False`` reads a
    .blf with can.LogReader frame by frame (the reference the fast path is tested against)."""
    rec = CanRecording(path, options.dbc, fast, options.instance)
    rec.decoder.mark_conflicts = True  # both copies of a conflicting sample are dropped (stream.py)
    log = messages_to_log(rec.messages(), path)
    for k, v in rec.counts.items():
        if v and (k in ("error_frames", "truncated_bytes") or k.startswith("blf_")):
            log.dropped[k] = int(v)
    for k, v in rec.stats().items():  # the decoder's counters, read once the generator has run
        if k not in ("frames", "bytes", "foreign_frames") and v:
            log.dropped[k] = int(v)
    log.metadata["host_frames"] = str(rec.counts["host_frames"])
    log.metadata["can_frames"] = str(rec.stats().get("frames", 0))
    foreign = int(rec.stats().get("foreign_frames", 0))
    if foreign:
        log.metadata["foreign_frames"] = str(foreign)
    if len(log) == 0 and foreign:
        nodes = _protocol_nodes(path, options.instance, options.dbc)
        if nodes:
            seen = ", ".join(f"node {n} ({c} frames)" for n, c in sorted(nodes.items()))
            raise LogFormatError(f"{path}: no sample of the unit on node {options.instance}; frames of "
                                 f"gyrocal's protocol come from {seen}: give that node id with --instance N")
        raise LogFormatError(f"{path}: none of its {foreign} frames carries an id of gyrocal's protocol "
                             "(0x100-0x1FF, docs/protocol.md section 3): not a recording of a gyrocal unit's "
                             "bus")
    return log


def _protocol_nodes(path: str, skip: int, dbc: str | None) -> collections.Counter[int]:
    """Frames per node id whose standard id is one of gyrocal's (0x100 + function << 4 + node), other
    than ``skip``: the advice of a log with no sample of the node asked for. Every node id was given
    the same "--instance N" advice, also for a log of another protocol, where no N could help (a
    foreign-log audit). Read again frame by frame: only on that error."""
    import can

    from gyrocal.protocol.can_codec import ID_BASE, load_dbc

    functions = {(m.frame_id - ID_BASE) >> 4 for m in load_dbc(dbc).messages}
    nodes: collections.Counter[int] = collections.Counter()
    try:
        for frame in can.LogReader(path):
            fid = frame.arbitration_id
            if (not frame.is_extended_id and not frame.is_error_frame and ID_BASE <= fid < ID_BASE + 0x100
                    and (fid - ID_BASE) >> 4 in functions and fid & 0xF != skip):
                nodes[fid & 0xF] += 1
    except Exception:  # noqa: BLE001 - the first pass read it; a cut tail here only shortens the advice
        pass
    return nodes
