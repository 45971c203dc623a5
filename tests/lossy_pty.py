"""A serial line that loses bursts of bytes: a pty the daemon opens, in front of the unit's pty.

Why: a USB-serial adapter whose buffer overruns drops a run of bytes, cut anywhere, frames and all.
The unit never knows, so its dT/dt rule goes on over samples the host never saw. This proxy copies
the unit's bytes to the host except during ``burst_s`` of every ``every_s`` (wall time), and the
host's bytes to the unit untouched, over real ptys, so the daemon's own decoder and session see
what such a line delivers.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty


class LossyPty:
    """Forward ``unit_path`` <-> a new pty (``address``), dropping unit bytes in periodic bursts."""

    CUT_BYTES = 7
    """Bytes lost after each burst as well, so that the line resumes inside a frame."""

    def __init__(self, unit_path: str, burst_s: float, every_s: float) -> None:
        self.burst_s, self.every_s = burst_s, every_s
        self._unit = os.open(unit_path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self._unit)
        self._master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(self._master, False)  # a host not reading yet loses bytes, as on a line
        self.address = os.ttyname(slave)
        self._slave = slave  # kept open so the master never sees EOF while the daemon reopens
        self.dropped_bytes = 0
        self._cut = False
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="lossy-pty", daemon=True)
        self._thread.start()

    def _losing(self) -> bool:
        return (time.monotonic() - self._t0) % self.every_s < self.burst_s

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._unit, self._master], [], [], 0.05)
                for fd in ready:
                    data = os.read(fd, 4096)
                    if fd == self._unit:
                        if self._losing():
                            self.dropped_bytes += len(data)
                            self._cut = True
                            continue
                        if self._cut:  # the burst ends inside a frame: its head is lost too
                            self._cut = False
                            self.dropped_bytes += min(len(data), self.CUT_BYTES)
                            data = data[self.CUT_BYTES:]
                        try:
                            os.write(self._master, data)
                        except BlockingIOError:
                            self.dropped_bytes += len(data)
                    else:
                        os.write(self._unit, data)
            except OSError:
                time.sleep(0.05)  # the unit restarting its pty, or the host not there yet

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for fd in (self._unit, self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
