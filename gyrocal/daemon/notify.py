"""sd_notify for the systemd service: READY=1, STATUS=, WATCHDOG=1, RELOADING=1, STOPPING=1.

Why a wrapper around sdnotify.SystemdNotifier: the daemon calls these from several places (the link
setup, the estimator loop, the signal handlers) and none of them should care whether systemd is
there. With NOTIFY_SOCKET unset (a terminal, the tests, the demo) every call is a cheap no-op. A
failing send is logged once and never raised: the daemon must not die because the notify socket did.

sdnotify 0.3.2 already maps a leading '@' in NOTIFY_SOCKET to the abstract namespace ('\\0'), which is
what systemd may pass, so we let it open and connect the datagram socket. We construct it with
debug=True so that errors reach us (to be logged) instead of being swallowed silently, and only when
NOTIFY_SOCKET is set (otherwise it would open a socket it can never use). We send on its socket
ourselves: its notify() encodes Latin-1, which would garble a UTF-8 STATUS such as "25 °C", and a
send timeout keeps a wedged systemd from blocking the estimator loop.

The watchdog: with WatchdogSec=10 systemd sets WATCHDOG_USEC=10000000 (and WATCHDOG_PID). The
estimator loop sends WATCHDOG=1 every watchdog_interval_s() (half the timeout, as sd_watchdog_enabled(3)
recommends) so a stuck loop stops the pings and systemd restarts the service.
"""

from __future__ import annotations

import logging
import os
import threading
import time

log = logging.getLogger(__name__)

_SEND_TIMEOUT_S = 1.0


class Notifier:
    """Send sd_notify state changes to systemd; a no-op when not started by systemd.

    Thread-safe: each call is one datagram, and the socket is only created once.
    """

    def __init__(self) -> None:
        env = os.environ
        self.socket_address = env.get("NOTIFY_SOCKET") or None
        self._watchdog_usec = env.get("WATCHDOG_USEC")
        self._watchdog_pid = env.get("WATCHDOG_PID")
        self._lock = threading.Lock()
        self._notifier = None
        self._failed_once = False
        self.sent = 0
        if self.socket_address:
            import sdnotify

            try:
                self._notifier = sdnotify.SystemdNotifier(debug=True)
                self._notifier.socket.settimeout(_SEND_TIMEOUT_S)
            except (OSError, TypeError) as err:
                log.warning("sd_notify: cannot connect to NOTIFY_SOCKET=%s: %s; systemd will not see "
                            "READY/WATCHDOG", self.socket_address, err)
                self._notifier = None

    @property
    def enabled(self) -> bool:
        """True when started by systemd with a notify socket we could connect to."""
        return self._notifier is not None

    def notify(self, state: str) -> bool:
        """Send one raw sd_notify message (newline-separated KEY=VALUE lines). True if it was sent."""
        if self._notifier is None:
            return False
        with self._lock:
            try:
                self._notifier.socket.sendall(state.encode("utf-8", "replace"))
            except OSError as err:
                if not self._failed_once:
                    log.warning("sd_notify: send to %s failed: %s (further failures are not logged)",
                                self.socket_address, err)
                    self._failed_once = True
                return False
            self.sent += 1
            return True

    def ready(self, status: str | None = None) -> bool:
        """READY=1: the links are open and the daemon serves. Also call it after a reload finishes."""
        return self.notify("READY=1" + (f"\nSTATUS={_one_line(status)}" if status else ""))

    def status(self, text: str) -> bool:
        """STATUS=...: the one line `systemctl status gyrocal` shows (e.g. 'unit 1234: COLLECTING 40%')."""
        return self.notify(f"STATUS={_one_line(text)}")

    def watchdog(self) -> bool:
        """WATCHDOG=1: the estimator loop is alive. Send every watchdog_interval_s()."""
        return self.notify("WATCHDOG=1")

    def reloading(self) -> bool:
        """RELOADING=1 on SIGHUP, before re-reading the config; call ready() when done.

        MONOTONIC_USEC is required by Type=notify-reload (systemd >= 253) and ignored by older ones.
        """
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify(f"RELOADING=1\nMONOTONIC_USEC={usec}")

    def stopping(self) -> bool:
        """STOPPING=1 on SIGTERM, before closing links and the store."""
        return self.notify("STOPPING=1")

    def extend_timeout(self, seconds: float) -> bool:
        """EXTEND_TIMEOUT_USEC: ask for more time to start or stop (e.g. a slow push in flight)."""
        return self.notify(f"EXTEND_TIMEOUT_USEC={int(seconds * 1e6)}")

    def watchdog_interval_s(self) -> float | None:
        """Half of WATCHDOG_USEC in seconds, or None when the watchdog is off or meant for another pid."""
        if not self._watchdog_usec:
            return None
        if self._watchdog_pid:
            try:
                if int(self._watchdog_pid) != os.getpid():
                    return None
            except ValueError:
                log.warning("sd_notify: ignoring bad WATCHDOG_PID=%r", self._watchdog_pid)
                return None
        try:
            usec = int(self._watchdog_usec)
        except ValueError:
            log.warning("sd_notify: ignoring bad WATCHDOG_USEC=%r", self._watchdog_usec)
            return None
        if usec <= 0:
            return None
        return usec / 2e6


def _one_line(text: str) -> str:
    """A newline would start a new KEY=VALUE assignment; keep STATUS to one line."""
    return " ".join(str(text).split())
