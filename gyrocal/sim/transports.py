"""The virtual unit's side of the wire: a pty pair (serial) or a python-can bus.

A transport sends messages (encoding them with the protocol) and polls for host requests. It never
blocks the unit's sample clock for long:

- ``PtyTransport`` owns the master side of a pty pair and keeps its own slave descriptor open, so
  the daemon may open, close and reopen the slave path (``path``) at will. The slave is put in raw
  mode at once (no echo, no line editing), as a real UART is. Writes are non-blocking into a bounded
  backlog: a unit that nobody listens to drops whole frames (``tx_dropped_frames``), it never stalls.
- ``CanTransport`` opens ``can.Bus(**bus_kwargs)`` and splits each message into frames with the
  protocol's ``CanCodec``.
"""

from __future__ import annotations

import binascii
import errno
import logging
import math
import os
import select
import struct
import tty
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import can
import numpy as np

from gyrocal.errors import ConfigError, LinkError
from gyrocal.protocol.serial_framing import SYNC, T_COEFF_REPORT, FrameDecoder, encode_frame
from gyrocal.sim.unit import NanReport

log = logging.getLogger(__name__)


class PtyTransport:
    """The unit's end of a fresh pty pair; ``path`` is the slave device the daemon opens.

    ``link_path``: also create a symlink there to the slave, so a daemon config can name a stable
    path (an existing symlink is replaced; any other file there is an error).
    ``max_backlog_bytes``: frames that do not fit are dropped whole and counted.
    ``garbage_rate``: probability per frame of a 1..16 byte burst of random garbage before it
    (drawn from ``rng``, so it is deterministic for a seed).
    """

    kind = "pty"

    def __init__(
        self, link_path: str | None = None, *, max_backlog_bytes: int = 1 << 20,
        garbage_rate: float = 0.0, rng: np.random.Generator | None = None,
    ) -> None:
        self._master, self._slave = os.openpty()
        self.link_path = None
        try:
            tty.setraw(self._slave)
            os.set_blocking(self._master, False)
            self.path = os.ttyname(self._slave)
            if link_path:
                _replace_symlink(Path(link_path), self.path)
        except BaseException:
            self.close()
            raise
        self.link_path = link_path
        self.max_backlog_bytes = max_backlog_bytes
        self.garbage_rate = garbage_rate
        self._rng = rng or np.random.default_rng(0)
        self._backlog = bytearray()
        self._decoder = FrameDecoder()
        self.stats = {"frames_sent": 0, "bytes_sent": 0, "tx_dropped_frames": 0, "garbage_bytes": 0}

    def describe(self) -> str:
        return self.path

    def reopen(self) -> None:
        """A cable replug: this pty pair goes away and a new one takes its place (and the symlink).
        The unit keeps running; the host sees its port vanish and come back."""
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        if self.link_path:
            _replace_symlink(Path(self.link_path), self.path)
        self._backlog.clear()
        self._decoder.reset()

    def send(self, msgs: Iterable[Any]) -> None:
        """Queue and write the frames of ``msgs``; never blocks."""
        out = bytearray()
        for m in msgs:
            if self.garbage_rate > 0 and self._rng.random() < self.garbage_rate:
                junk = self._rng.integers(0, 256, int(self._rng.integers(1, 17)), dtype=np.uint8).tobytes()
                out += junk
                self.stats["garbage_bytes"] += len(junk)
            frame = nan_report_frame(m) if isinstance(m, NanReport) else encode_frame(m)
            if len(self._backlog) + len(out) + len(frame) > self.max_backlog_bytes:
                self.stats["tx_dropped_frames"] += 1
                continue
            out += frame
            self.stats["frames_sent"] += 1
        self._backlog += out
        self.flush()

    def flush(self) -> None:
        """Write as much of the backlog as the pty takes now."""
        while self._backlog:
            try:
                n = os.write(self._master, self._backlog)
            except BlockingIOError:
                return
            except OSError as err:  # EIO: nobody holds the slave (cannot happen while we hold it)
                if err.errno == errno.EIO:
                    return
                raise
            self.stats["bytes_sent"] += n
            del self._backlog[:n]

    @property
    def backlog_bytes(self) -> int:
        return len(self._backlog)

    def poll(self, timeout_s: float) -> list[Any]:
        """Wait up to ``timeout_s`` [s] for host frames (writing the backlog meanwhile); decode them."""
        wlist = [self._master] if self._backlog else []
        try:
            r, w, _ = select.select([self._master], wlist, [], max(0.0, timeout_s))
        except InterruptedError:
            return []
        if w:
            self.flush()
        if not r:
            return []
        try:
            data = os.read(self._master, 65536)
        except (BlockingIOError, InterruptedError):
            return []
        except OSError as err:
            if err.errno == errno.EIO:
                return []
            raise
        return self._decoder.feed(data)

    def close(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self._master = self._slave = -1
        if self.link_path:
            p = Path(self.link_path)
            if p.is_symlink() and os.readlink(p) == self.path:
                p.unlink()


def nan_report_payload(m: NanReport) -> bytes:
    """The canonical coefficient-set bytes (docs/protocol.md) of a set of NaNs, built by hand."""
    return struct.pack("<IHB", m.version, m.terms_id, m.n_terms) + struct.pack(
        f"<{3 * m.n_terms}d", *([math.nan] * (3 * m.n_terms)))


def nan_report_frame(m: NanReport) -> bytes:
    """A serial COEFF_REPORT frame carrying NaNs, with a valid frame CRC-32."""
    payload = nan_report_payload(m)
    head = struct.pack("<BH", T_COEFF_REPORT, len(payload))
    return SYNC + head + payload + struct.pack("<I", binascii.crc32(payload, binascii.crc32(head)))


def _replace_symlink(link: Path, target: str) -> None:
    if link.is_symlink():
        link.unlink()
    elif link.exists():
        raise ConfigError(f"--pty-link {link}: a file that is not a symlink is there; "
                          "remove it or pick another path")
    try:
        link.symlink_to(target)
    except OSError as err:
        raise ConfigError(f"--pty-link {link}: cannot create the symlink ({err.strerror}); "
                          "pick a writable path") from err


class CanTransport:
    """The unit on a python-can bus. ``bus_kwargs`` go to ``can.Bus`` unchanged."""

    kind = "can"

    def __init__(self, bus_kwargs: dict[str, Any], *, dbc_path: str | None = None, node_id: int = 0) -> None:
        from gyrocal.drivers.can_link import check_bus_kwargs

        self.bus_kwargs = check_bus_kwargs(bus_kwargs)
        try:
            self.bus = can.Bus(**self.bus_kwargs)
        except (can.CanError, OSError, ValueError, TypeError, ImportError) as err:
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise LinkError(f"CAN bus {self.bus_kwargs} cannot be opened ({reason}); check interface, "
                            "channel and port") from err
        from gyrocal.drivers.can_link import enlarge_receive_buffer, frame_ids_sent_by
        from gyrocal.protocol.can_codec import CanCodec

        enlarge_receive_buffer(self.bus)
        self._codec = CanCodec(dbc_path, node_id=node_id)
        self._decoder = self._codec.decoder()
        self._accept = frame_ids_sent_by(self._codec, "HOST")  # not our own looped-back frames
        self.stats = {"frames_sent": 0, "tx_errors": 0}

    def describe(self) -> str:
        return " ".join(f"{k}={v}" for k, v in self.bus_kwargs.items())

    def send(self, msgs: Iterable[Any]) -> None:
        for m in msgs:
            frames = self._nan_report(m) if isinstance(m, NanReport) else self._codec.encode(m)
            for frame in frames:
                try:
                    self.bus.send(frame)
                    self.stats["frames_sent"] += 1
                except (can.CanError, OSError):
                    self.stats["tx_errors"] += 1

    def _nan_report(self, m: NanReport) -> list[can.Message]:
        """REPORT_BEGIN / DATA / END of a NaN set with a matching CRC (the codec refuses to encode it)."""
        payload = nan_report_payload(m)
        words = struct.unpack(f"<{(len(payload) - 7) // 4}I", payload[7:])
        c = self._codec
        frames = [c._frame("REPORT_BEGIN",
                           {"CAL_VERSION": m.version, "TERMS_ID": m.terms_id, "N_TERMS": m.n_terms})]
        frames += [c._frame("REPORT_DATA", {"CHUNK": k, "CAL_VERSION_LO": m.version & 0xFFFF, "WORD": w})
                   for k, w in enumerate(words)]
        frames.append(c._frame("REPORT_END", {"CAL_VERSION": m.version, "CRC": binascii.crc32(payload)}))
        return frames

    def flush(self) -> None:
        """Nothing is queued on our side."""

    backlog_bytes = 0

    def poll(self, timeout_s: float) -> list[Any]:
        out: list[Any] = []
        frame = self.bus.recv(max(0.0, timeout_s))
        budget = 1000
        while frame is not None and budget > 0:
            if self._accept is None or frame.arbitration_id in self._accept:
                out.extend(self._decoder.feed(frame))
            frame = self.bus.recv(0.0)
            budget -= 1
        return out

    def close(self) -> None:
        self.bus.shutdown()

