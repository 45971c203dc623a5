"""Reader ``serial``: a capture of the serial link's raw bytes (docs/protocol.md framing).

The bytes go through the live link's ``FrameDecoder`` in 64 KiB pieces, so garbage, resyncs and
CRC failures are handled and counted exactly as on the wire. Such a capture is what ``cat
/dev/ttyUSB0 > run.cap`` or a logic analyser's UART export gives.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData
from gyrocal.protocol.serial_framing import FrameDecoder
from gyrocal.readers import ReadOptions
from gyrocal.readers.stream import messages_to_log

CHUNK = 1 << 16


class SerialRecording:
    """The unit messages of a byte capture, in order; ``decoder.stats`` after use."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.decoder = FrameDecoder()

    def messages(self) -> Iterator[Any]:
        try:
            fh = open(self.path, "rb")  # closed by the with below
        except OSError as err:
            raise LogFormatError(f"{self.path}: cannot open the capture ({err.strerror})") from err
        with fh:
            while chunk := fh.read(CHUNK):
                yield from self.decoder.feed(chunk)

    def stats(self) -> dict[str, int]:
        return self.decoder.stats.as_dict()


def read_serial_capture(path: str, options: ReadOptions) -> LogData:
    """A serial byte capture's SAMPLEs as log columns; HELLOs split sessions."""
    rec = SerialRecording(path)
    rec.decoder.mark_conflicts = True  # both copies of a conflicting sample are dropped (stream.py)
    log = messages_to_log(rec.messages(), path)
    for k, v in rec.stats().items():
        if k not in ("frames", "bytes", "foreign_frames") and v:
            log.dropped[k] = int(v)
    if rec.decoder.buffered:  # a frame cut by the end of the capture
        log.dropped["truncated_bytes"] = int(rec.decoder.buffered)
    return log
