"""The serial link: any pyserial URL (``/dev/ttyUSB0``, a pty path, ``socket://host:port``, ``loop://``).

The port is opened with ``serial.serial_for_url`` so every pyserial transport works unchanged. The
reader thread reads whatever is waiting (at least one byte, or ``poll_s`` of silence) and feeds it to
the protocol's ``FrameDecoder``, which handles garbage, resync and CRC (see docs/protocol.md).

A vanished device shows up as ``SerialException`` / ``OSError`` on read: a USB adapter unplugged,
or a pty whose master side (the virtual unit) has exited, which reads as EIO or as "ready but no
data". The base class then closes the port and reopens it with backoff until the device returns.
"""

from __future__ import annotations

from typing import Any

import serial

from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers.base import ControlCallback, EventCallback, Link
from gyrocal.errors import LinkError
from gyrocal.protocol.serial_framing import FrameDecoder, encode_frame

DEFAULT_BAUDRATE = 921600
"""The unit's default line rate [bit/s]; ignored by ptys, sockets and loop://."""


def _fix_hint(url: str, err: BaseException | None = None) -> str:
    if "://" in url:
        return "check the URL and that the server behind it is running"
    errno_ = getattr(err, "errno", None)
    if errno_ is None and isinstance(err.__context__ if err is not None else None, OSError):
        errno_ = err.__context__.errno  # pyserial wraps the OSError
    if "exclusively lock" in str(err or ""):  # pyserial's exclusive open: another process holds it
        return ("another process holds the port open (another gyrocal daemon?): fuser -v " + url
                + " names it; stop it, the daemon opens the port when it is free")
    if errno_ == 13 or "Permission denied" in str(err or ""):  # EACCES: the port is there
        return ("this user may not open it: add it to the port's group (ls -l the device; usually "
                "dialout), or fix the udev rule's GROUP/MODE")
    return ("check that the unit is plugged in and the path is right (ls /dev/ttyUSB* /dev/serial/by-id/), "
            "and that this user may open it (group dialout)")


class SerialLink(Link):
    """A link over a serial port or any pyserial URL.

    ``url``: a device path or pyserial URL. ``baudrate`` [bit/s]. ``write_timeout_s`` [s]: a write
    that cannot complete in this time fails (``LinkError``) rather than blocking the caller.
    """

    kind = "serial"
    _io_errors = (OSError, serial.SerialException)

    def __init__(
        self, url: str, ring: RingBuffer, on_control: ControlCallback, on_event: EventCallback | None = None,
        baudrate: int = DEFAULT_BAUDRATE, *, write_timeout_s: float = 1.0, **link_kwargs: Any,
    ) -> None:
        super().__init__(ring, on_control, on_event, **link_kwargs)
        self.url = str(url)
        self.baudrate = int(baudrate)
        self.write_timeout_s = write_timeout_s
        self._port: serial.SerialBase | None = None
        self._decoder = FrameDecoder()
        self._bytes_sent = 0

    @property
    def target(self) -> str:
        return self.url

    def _open(self) -> None:
        try:
            # exclusive: a second daemon on the same port (its own state_dir and socket) took half the
            # bytes of each, both flapping link_lost / link_up 4 times a second (two outside audits);
            # now its open fails with one line, as the reconnect loop says
            port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=self.poll_s,
                                         write_timeout=self.write_timeout_s, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as err:
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            msg = f"serial port {self.url!r} cannot be opened ({reason}); {_fix_hint(self.url, err)}"
            raise LinkError(msg) from err
        self._port = port
        self._decoder.reset()  # bytes of a frame cut by the last disconnect are not resumed

    def _close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            port.close()

    def _receive(self) -> list[Any]:
        port = self._port
        if port is None:
            raise OSError("port closed")
        data = port.read(port.in_waiting or 1)
        if not data:
            return []
        return self._decoder.feed(data)

    def _transmit(self, msg: Any) -> None:
        port = self._port
        if port is None:
            raise OSError("port closed")
        frame = encode_frame(msg)
        port.write(frame)
        self._bytes_sent += len(frame)

    def _decoder_stats(self) -> dict[str, int]:
        return self._decoder.stats.as_dict()

    def _transport_stats(self) -> dict[str, int]:
        return {"bytes_sent": self._bytes_sent}

