"""sd_notify, emulated: a local AF_UNIX datagram socket stands in for systemd's NOTIFY_SOCKET."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

from gyrocal.daemon.notify import Notifier

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def notify_socket(monkeypatch) -> Iterator[socket.socket]:
    """A bound datagram socket, exported as NOTIFY_SOCKET, as systemd does for Type=notify."""
    d = Path(tempfile.mkdtemp(prefix="gcn", dir="/tmp"))
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(os.fspath(d / "notify"))
    sock.settimeout(10)
    monkeypatch.setenv("NOTIFY_SOCKET", os.fspath(d / "notify"))
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    yield sock
    sock.close()
    shutil.rmtree(d, ignore_errors=True)


def recv(sock: socket.socket) -> str:
    return sock.recv(4096).decode()


def test_without_notify_socket_every_call_is_a_no_op(monkeypatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = Notifier()
    assert not n.enabled
    assert [n.ready(), n.status("x"), n.watchdog(), n.reloading(), n.stopping()] == [False] * 5


def test_messages_reach_the_socket_in_the_sd_notify_format(notify_socket) -> None:
    n = Notifier()
    assert n.enabled
    assert n.ready()
    assert recv(notify_socket) == "READY=1"
    n.ready("links open")
    assert recv(notify_socket) == "READY=1\nSTATUS=links open"
    n.status("unit 1234: COLLECTING\n40 %, 25 °C")
    assert recv(notify_socket) == "STATUS=unit 1234: COLLECTING 40 %, 25 °C"  # one line, UTF-8 kept
    n.watchdog()
    assert recv(notify_socket) == "WATCHDOG=1"
    n.reloading()
    first, second = recv(notify_socket).split("\n")
    assert first == "RELOADING=1" and second.startswith("MONOTONIC_USEC=") and int(second.split("=")[1]) > 0
    n.extend_timeout(30)
    assert recv(notify_socket) == "EXTEND_TIMEOUT_USEC=30000000"
    n.stopping()
    assert recv(notify_socket) == "STOPPING=1"
    assert n.sent == 7


def test_abstract_socket_address_with_at_prefix(monkeypatch) -> None:
    name = f"gyrocal-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(10)
    monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
    try:
        assert Notifier().ready()
        assert recv(sock) == "READY=1"
    finally:
        sock.close()


def test_a_vanished_notify_socket_is_logged_once_and_never_raises(notify_socket, caplog) -> None:
    n = Notifier()
    os.unlink(os.environ["NOTIFY_SOCKET"])
    notify_socket.close()
    assert n.watchdog() is False and n.watchdog() is False
    assert caplog.text.count("send to") == 1


def test_a_notify_socket_that_does_not_exist_disables_notifications(monkeypatch, caplog) -> None:
    monkeypatch.setenv("NOTIFY_SOCKET", "/nonexistent/gyrocal/notify")
    n = Notifier()
    assert not n.enabled and n.ready() is False
    assert "cannot connect" in caplog.text


@pytest.mark.parametrize(("usec", "pid", "expected"), [
    (None, None, None),
    ("10000000", None, 5.0),
    ("10000000", "self", 5.0),
    ("10000000", "1", None),  # meant for another process (e.g. our parent)
    ("0", None, None),
    ("ten", None, None),
    ("10000000", "x", None),
])
def test_watchdog_interval_is_half_of_watchdog_usec_for_our_pid(monkeypatch, usec, pid, expected) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    for key, value in (("WATCHDOG_USEC", usec), ("WATCHDOG_PID", pid)):
        if value is None:
            monkeypatch.delenv(key, raising=False)
        else:
            monkeypatch.setenv(key, str(os.getpid()) if value == "self" else value)
    assert Notifier().watchdog_interval_s() == expected


# A stand-in for the daemon's use of the Notifier: READY=1 once up, WATCHDOG=1 every interval from
# its loop, STOPPING=1 on SIGTERM. The daemon core has its own end-to-end test of the real loop.
# The handler only appends to a list (no lock): an Event.set() in it could interrupt stop.wait()
# holding the Event's lock and wait for it forever, the deadlock the daemon's own handlers had (see
# tests/test_daemon_signals.py). A fresh-clone CI run timed out here once; that is the likely cause.
CHILD = textwrap.dedent("""
    import signal, sys, time
    from gyrocal.daemon.notify import Notifier
    stop = []
    signal.signal(signal.SIGTERM, lambda *a: stop.append(True))
    n = Notifier()
    interval = n.watchdog_interval_s()
    assert interval is not None, "WATCHDOG_USEC not seen"
    n.ready("links open")
    while not stop:
        time.sleep(interval)
        if not stop:
            n.watchdog()
    n.stopping()
    sys.exit(0)
""")


def test_process_sends_ready_then_periodic_watchdog_then_stopping_on_sigterm(notify_socket) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "WATCHDOG_USEC": "100000"}  # WatchdogSec=0.1
    env.pop("WATCHDOG_PID", None)
    proc = subprocess.Popen([sys.executable, "-c", CHILD], env=env, cwd=REPO)
    try:
        assert recv(notify_socket) == "READY=1\nSTATUS=links open"
        for _ in range(3):
            assert recv(notify_socket) == "WATCHDOG=1"
        proc.send_signal(signal.SIGTERM)
        while (msg := recv(notify_socket)) == "WATCHDOG=1":
            pass
        assert msg == "STOPPING=1"
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
