"""Reader ``can``: python-can log files (.asc, .blf, candump .log, .trc, .mf4, ...) with our DBC.

``can.LogReader`` picks the file reader by extension, so every format python-can reads works here.
Frames go through the same ``CanDecoder`` as the live CAN link, and, as there, only frames the DBC
marks as sent by the UNIT are decoded: a bus recording also holds the host's COEFF_READ/WRITE
frames (counted as ``host_frames``, not dropped data). Error and remote frames are counted apart.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData
from gyrocal.readers import ReadOptions
from gyrocal.readers.stream import messages_to_log


class CanRecording:
    """The unit messages of a python-can log, in file order, with the decoder's counters after use."""

    def __init__(self, path: str, dbc: str | None = None) -> None:
        import can

        from gyrocal.drivers.can_link import frame_ids_sent_by
        from gyrocal.protocol.can_codec import CanCodec

        if not Path(path).exists():
            raise LogFormatError(f"{path}: cannot open the log (no such file)")
        self.path = path
        self._can = can
        self.codec = CanCodec(dbc)
        self.decoder = self.codec.decoder()
        self.accept = frame_ids_sent_by(self.codec, "UNIT")
        self.counts = {"host_frames": 0, "error_frames": 0}

    def messages(self) -> Iterator[Any]:
        """Decoded unit messages (Sample, Hello, CoeffReport, ...) in the order of the file."""
        try:
            reader = self._can.LogReader(self.path)
        except Exception as err:  # unknown suffix, unreadable file, BLFParseError, ...
            raise LogFormatError(f"{self.path}: python-can cannot read it ({err})") from err
        accept, feed, counts = self.accept, self.decoder.feed, self.counts
        try:
            for frame in reader:
                if frame.is_error_frame:
                    counts["error_frames"] += 1
                    continue
                if accept is not None and frame.arbitration_id in accept:
                    yield from feed(frame)
                elif accept is not None and not frame.is_extended_id and frame.arbitration_id >> 8 == 1:
                    counts["host_frames"] += 1
                else:
                    yield from feed(frame)  # the decoder counts foreign frames itself
        except Exception as err:  # python-can's readers raise their own errors on a damaged file
            if isinstance(err, LogFormatError):
                raise
            raise LogFormatError(f"{self.path}: python-can failed while reading it ({err})") from err
        finally:
            stop = getattr(reader, "stop", None)
            if stop is not None:
                stop()

    def stats(self) -> dict[str, int]:
        return self.decoder.stats.as_dict()


def read_canlog(path: str, options: ReadOptions) -> LogData:
    """A python-can log's SAMPLEs as log columns; HELLOs split sessions."""
    rec = CanRecording(path, options.dbc)
    log = messages_to_log(rec.messages(), path)
    if rec.counts["error_frames"]:
        log.dropped["error_frames"] = rec.counts["error_frames"]
    for k, v in rec.stats().items():  # the decoder's counters, read once the generator has run
        if k not in ("frames", "bytes", "foreign_frames") and v:
            log.dropped[k] = int(v)
    log.metadata["host_frames"] = str(rec.counts["host_frames"])
    log.metadata["can_frames"] = str(rec.stats().get("frames", 0))
    return log
