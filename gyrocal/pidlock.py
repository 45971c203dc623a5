"""An exclusive, non-blocking lock on a file that names its holder: one daemon per store, per port.

Why one module: the state directory's lock (daemon/engine.py) and the serial port's claim
(drivers/serial_link.py) took and reported their locks with two copies of the same steps. The lock
is flock(2): the kernel drops it when the holder dies, so a crash never leaves a stale lock behind;
the file's text ("pid N") only says who holds it.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import IO


def take(path: Path) -> tuple[IO[str] | None, str]:
    """Lock ``path`` (created if absent) without waiting: (its open file, "") when taken, else (None,
    the holder's text, or "a process" when it wrote none). OSError when the file cannot be opened."""
    fh = path.open("a+", encoding="utf-8")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.seek(0)
        holder = fh.read().strip() or "a process"
        fh.close()
        return None, holder
    return fh, ""


def write_pid(fh: IO[str]) -> None:
    """Write "pid N" (this process) into a lock file taken with ``take``; OSError on a full disk."""
    fh.seek(0)
    fh.truncate()
    fh.write(f"pid {os.getpid()}\n")
    fh.flush()
