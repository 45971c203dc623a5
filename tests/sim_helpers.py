"""Shared by the driver and simulator tests: run ``gyrocal sim`` as a separate process."""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

SIM_CMD = [sys.executable, "-m", "gyrocal.cli", "sim"]


def free_udp_port() -> int:
    """A UDP port no one uses now: distinct per test run, so parallel runs do not collide."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


MULTICAST_GROUP = "239.74.163.2"


def multicast_works(port: int) -> bool:
    """True when python-can udp_multicast loops a datagram back on this host (it needs a route)."""
    import can

    try:
        bus = can.Bus(interface="udp_multicast", channel=MULTICAST_GROUP, port=port)
    except (can.CanError, OSError):
        return False
    try:
        bus.send(can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False))
        return bus.recv(1.0) is not None
    except (can.CanError, OSError):
        return False
    finally:
        bus.shutdown()


def wait_for(cond: Callable[[], bool], timeout_s: float = 20.0, poll_s: float = 0.01) -> bool:
    """Poll ``cond`` until it holds or ``timeout_s`` passes (a generous bound, never asserted on)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(poll_s)
    return cond()


class SimProcess:
    """``gyrocal sim ARGS`` in a child process; ``address`` is the first line it prints."""

    def __init__(self, *args: str, tmp_path: Path, timeout_s: float = 20.0) -> None:
        self.stderr_path = tmp_path / f"sim-{time.monotonic_ns()}.stderr"
        self._stderr = self.stderr_path.open("wb")
        self.proc = subprocess.Popen([*SIM_CMD, *args], stdout=subprocess.PIPE, stderr=self._stderr,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s)
        line = self.proc.stdout.readline().decode().strip() if ready else ""
        if not line:
            self.stop()
            raise RuntimeError(f"gyrocal sim printed no address; stderr: {self.stderr_path.read_text()}")
        self.address = line

    def power_cycle(self) -> None:
        self.proc.send_signal(signal.SIGUSR1)

    def stop(self, timeout_s: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        self._stderr.close()
        if self.proc.stdout:
            self.proc.stdout.close()
        return rc

    def __enter__(self) -> SimProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def read_status(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.exists() else {}


EXTENDED = bool(os.environ.get("GYROCAL_EXTENDED"))
"""Cases that repeat another's coverage on a second transport, node or set-up run only with
GYROCAL_EXTENDED=1, so the suite stays within its time budget (about 10 minutes on 2 cores)."""
EXTENDED_ONLY = pytest.mark.skipif(not EXTENDED, reason="repeats covered ground; run with GYROCAL_EXTENDED=1")
