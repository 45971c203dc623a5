"""Signals never hang the daemon's loop: SIGHUP, SIGUSR1 and SIGTERM arriving at any bytecode.

A fresh-clone CI run once saw a daemon that took a SIGHUP and then never sent RELOADING=1 nor another
watchdog ping: the handler had put into the engine's inbox while the loop, interrupted inside
``inbox.get_nowait()``, held the queue's lock. Under systemd the watchdog would have killed it.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml

HAMMER = r"""
import os, signal, sys, threading, time
from gyrocal.daemon.config import load_config
from gyrocal.daemon.engine import Engine

engine = Engine(load_config(sys.argv[1]))
engine.idle_sleep_s = 0.0  # a busy loop: it is inside inbox.get_nowait() most of the time
handled = {"reload": 0, "cmd": 0}
engine._reload = lambda: handled.__setitem__("reload", handled["reload"] + 1)
engine._command = lambda request, now: (handled.__setitem__("cmd", handled["cmd"] + 1), {"ok": True})[1]
engine.install_signals()

def hammer():
    for i in range(int(sys.argv[2])):
        os.kill(os.getpid(), signal.SIGHUP if i % 2 else signal.SIGUSR1)
        time.sleep(0.0005)
    time.sleep(0.2)
    os.kill(os.getpid(), signal.SIGTERM)

threading.Thread(target=hammer, daemon=True).start()
engine.run()
print(handled["reload"], handled["cmd"], flush=True)
"""


def test_a_storm_of_signals_never_hangs_the_loop(tmp_path: Path) -> None:
    cfg = tmp_path / "gyrocal.yaml"
    cfg.write_text(yaml.safe_dump({"state_dir": str(tmp_path / "state"), "watchdog": False,
                                   "control_socket": str(tmp_path / "c.sock"),
                                   "link": {"kind": "serial", "url": str(tmp_path / "none.pty")}}))
    try:
        out = subprocess.run([sys.executable, "-c", HAMMER, str(cfg), "600"], capture_output=True,
                             text=True, timeout=120)
    except subprocess.TimeoutExpired as err:  # the old handlers deadlocked here
        raise AssertionError("the engine loop hung under a storm of signals") from err
    assert out.returncode == 0, out.stderr[-2000:]
    reloads, cmds = (int(v) for v in out.stdout.split())
    # signals of one kind that arrive before the handler runs are merged by the OS; every one that
    # was handled became work, and SIGTERM then stopped the loop cleanly
    assert reloads >= 1 and cmds >= 1, out.stdout


def test_a_daemon_killed_by_sigkill_takes_its_virtual_unit_with_it(tmp_path: Path) -> None:
    """`gyrocal run` on the packaged default starts `gyrocal sim` as its child. A kill -9 of the daemon
    left that unit running, orphaned, on a pty nobody reads (an operator's audit); the unit now asks
    the kernel for SIGTERM when its parent dies (--parent-pid). The unit's directory, which a killed
    daemon cannot remove, is removed by the next daemon's sweep (and only a dead daemon's)."""
    import os
    import signal
    import time

    from gyrocal.daemon.cli_run import sweep_unit_dirs

    tmp = tmp_path / "t"
    tmp.mkdir()
    env = {**os.environ, "TMPDIR": str(tmp)}
    daemon = subprocess.Popen([sys.executable, "-m", "gyrocal.cli", "run", "--state-dir", str(tmp_path / "s"),
                               "--socket", str(tmp_path / "c.sock")], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, env=env)
    children: list[int] = []
    try:
        end = time.monotonic() + 30
        while time.monotonic() < end and not children:
            try:
                text = Path(f"/proc/{daemon.pid}/task/{daemon.pid}/children").read_text()
                children = [int(c) for c in text.split()]
            except OSError:
                pass
            time.sleep(0.2)
        assert children, "the daemon started no virtual unit"
        time.sleep(1.0)  # the unit is up and streaming
        daemon.send_signal(signal.SIGKILL)
        daemon.wait(10)
        end = time.monotonic() + 10
        while time.monotonic() < end and any(Path(f"/proc/{c}").exists() and
                                             "Z" not in _state(c) for c in children):
            time.sleep(0.1)
        assert not any(Path(f"/proc/{c}").exists() and "Z" not in _state(c) for c in children)
        left = list(tmp.glob(f"gyrocal-unit-{daemon.pid}-*"))
        assert len(left) == 1
        mine = tmp / f"gyrocal-unit-{os.getpid()}-live"  # a running daemon's: kept
        mine.mkdir()
        assert sweep_unit_dirs(tmp) == left and not left[0].exists() and mine.exists()
    finally:
        if daemon.poll() is None:
            daemon.kill()
        for c in children:
            try:
                os.kill(c, signal.SIGKILL)
            except OSError:
                pass


def _state(pid: int) -> str:
    """The process state letter from /proc/PID/stat ('' if it is gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return ""
