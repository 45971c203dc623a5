"""The serial link: any pyserial URL (``/dev/ttyUSB0``, a pty path, ``socket://host:port``, ``loop://``).

The port is opened with ``serial.serial_for_url`` so every pyserial transport works unchanged. The
reader thread reads whatever is waiting (at least one byte, or ``poll_s`` of silence) and feeds it to
the protocol's ``FrameDecoder``, which handles garbage, resync and CRC (see docs/protocol.md).

A vanished device shows up as ``SerialException`` / ``OSError`` on read: a USB adapter unplugged,
or a pty whose master side (the virtual unit) has exited, which reads as EIO or as "ready but no
data". The base class then closes the port and reopens it with backoff until the device returns.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import IO, Any

import serial

from gyrocal import pidlock
from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers.base import ControlCallback, EventCallback, Link
from gyrocal.errors import LinkError
from gyrocal.protocol.serial_framing import FrameDecoder, encode_frame

DEFAULT_BAUDRATE = 921600
"""The unit's default line rate [bit/s]; ignored by ptys, sockets and loop://."""

LOCK_DIR_ENV = "GYROCAL_LOCK_DIR"
"""Environment variable naming the port-claim directory (default /run/lock, FHS's lock directory)."""

log = logging.getLogger("gyrocal.drivers.serial")


def _claim_path(url: str) -> Path | None:
    """The claim file of a device path (None for a pyserial URL such as socket:// or loop://): one
    name per configured path, so a daemon keeps its port across a replug whatever the new tty is."""
    if "://" in url:
        return None
    name = re.sub(r"[^A-Za-z0-9._-]", "_", os.path.abspath(url).strip("/"))
    return Path(os.environ.get(LOCK_DIR_ENV, "/run/lock")) / f"gyrocal-{name}.lock"


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
        self._claim: IO[str] | None = None
        self._dev_claim: tuple[str, IO[str]] | None = None  # (device path, its lock) behind the url
        self._claim_said = False

    @property
    def target(self) -> str:
        return self.url

    def _take_claim(self) -> None:
        """Claim the port for this daemon's life, across unplugs: a lock on /run/lock/gyrocal-<path>.lock
        for the configured path, and one for the device it names now (``/dev/ttyUSB0`` behind a udev
        symlink), moved when a replug names another.

        Why: the exclusive open holds the port only while it is open. At a replug a second daemon
        (its own store, started by hand) could open the new tty first and calibrate the unit against
        another store: the service then read a foreign set (an outside audit said it, not prevented);
        one that named the port otherwise (``/dev/ttyUSB0`` beside ``/dev/gyrocal-imu``) took it once
        in 6 replugs (its re-check). A lock directory that cannot be written (a container without
        /run/lock) is said once, and the exclusive open alone guards the port then."""
        if self._claim is None:
            path = _claim_path(self.url)
            if path is None:
                return
            self._claim = self._lock(path)
            if self._claim is None:
                return
        dev = os.path.realpath(self.url)
        if dev == os.path.abspath(self.url) or not os.path.exists(dev):
            return
        held = self._dev_claim
        if held is not None and held[0] == dev:
            return
        path = _claim_path(dev)
        fh = self._lock(path) if path is not None else None
        if fh is not None:  # the device this path names now; the one it named before is let go
            self._dev_claim = (dev, fh)
            if held is not None:
                self._unlock(held[0], held[1])

    def _lock(self, path: Path) -> IO[str] | None:
        """An exclusive lock on ``path`` (written with this pid), None where locks cannot be made;
        LinkError when another daemon holds it."""
        try:
            fh, holder = pidlock.take(path)
        except OSError as err:
            if not self._claim_said:
                log.info("serial %s: no port claim in %s (%s): the exclusive open alone guards the port",
                         self.url, path.parent, err.strerror or err)
                self._claim_said = True
            return None
        if fh is None:
            raise LinkError(f"serial port {self.url!r} is claimed by another gyrocal daemon ({holder}; "
                            f"lock {path}): one daemon per port; stop it, this one takes the port when "
                            "it is free")
        try:
            same = os.fstat(fh.fileno()).st_ino == path.stat().st_ino
        except FileNotFoundError:
            same = False
        if not same:  # its holder removed it as we locked it (_unlock): claimed at the next open
            fh.close()
            raise LinkError(f"serial port {self.url!r}: its claim {path} was just released; taken next try")
        pidlock.write_pid(fh)
        return fh

    @staticmethod
    def _unlock(name: str, fh: IO[str]) -> None:
        """Removed while locked, then unlocked: a waiter checks that it locked the file still named."""
        path = _claim_path(name)
        if path is not None:
            path.unlink(missing_ok=True)
        fh.close()

    def start(self, wait: bool = True) -> None:
        try:
            super().start(wait)
        except LinkError:  # a one-shot open that failed (wait=True): nobody keeps this port
            self._release_claim()
            raise

    def stop(self, timeout_s: float = 2.0) -> None:
        super().stop(timeout_s)
        self._release_claim()

    def _release_claim(self) -> None:
        claim, self._claim = self._claim, None
        dev, self._dev_claim = self._dev_claim, None
        if claim is not None:
            self._unlock(self.url, claim)
        if dev is not None:
            self._unlock(dev[0], dev[1])

    def _open(self) -> None:
        self._take_claim()
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

