"""`gyrocal run`: the calibrator daemon, as systemd starts it.

With no ``--config`` the packaged default runs against the virtual unit (a child `gyrocal sim` on a
pty), so the daemon can be tried on any machine. On a vehicle the service passes
``--config /etc/gyrocal/gyrocal.yaml`` naming the real device.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
import shutil
import tempfile
from pathlib import Path

from gyrocal.daemon.config import load_config
from gyrocal.daemon.engine import Engine
from gyrocal.daemon.logsetup import setup_logging
from gyrocal.daemon.virtual import start_virtual_unit

log = logging.getLogger("gyrocal.run")


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="YAML config (default: the packaged virtual-unit config)")
    p.add_argument("--state-dir", help="override state_dir (calibration store)")
    p.add_argument("--socket", help="override control_socket")
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])


UNIT_DIR_PREFIX = "gyrocal-unit-"
"""The virtual unit's working directory (pty link, schedule, status) is ``<tmp>/gyrocal-unit-PID-*``,
PID the daemon's: a daemon killed by SIGKILL cannot remove it, so the next one does (sweep_unit_dirs)."""


def sweep_unit_dirs(tmp: Path | None = None) -> list[Path]:
    """Remove the virtual-unit directories of daemons that are gone (their PID runs nothing, and this
    user owns them); returns what was removed. A PID taken again by another process keeps its
    directory: only a dead owner's is removed, never a live one's."""
    removed = []
    root = Path(tmp or tempfile.gettempdir())
    for d in root.glob(f"{UNIT_DIR_PREFIX}*-*"):
        m = re.fullmatch(rf"{UNIT_DIR_PREFIX}(\d+)-\w+", d.name)
        try:
            if m is None or d.is_symlink() or not d.is_dir() or d.stat().st_uid != os.getuid():
                continue
            os.kill(int(m.group(1)), 0)
        except ProcessLookupError:
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
            log.info("removed %s, left by a daemon that was killed", d)
        except OSError:  # alive under another user (EPERM), or gone meanwhile
            continue
    return removed


def main(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    overrides = {}
    if args.state_dir:
        overrides["state_dir"] = args.state_dir
    if args.socket:
        overrides["control_socket"] = args.socket
    cfg = load_config(args.config, overrides)
    log.info("gyrocal daemon starting with %s", cfg.source)
    unit = None
    link_cfg = dict(cfg.link)
    workdir = contextlib.nullcontext(None)
    if cfg.virtual_unit["enabled"]:
        sweep_unit_dirs()
        workdir = tempfile.TemporaryDirectory(prefix=f"{UNIT_DIR_PREFIX}{os.getpid()}-")
    with workdir as tmp:
        if tmp is not None:
            unit = start_virtual_unit(cfg.virtual_unit, cfg.link["kind"], Path(tmp))
            link_cfg.update(unit.link_cfg)
            # a WARNING: on a vehicle this means the real unit is not being calibrated at all
            log.warning("virtual unit started (pid %d) on %s: calibrating a simulated unit, not hardware "
                        "(virtual_unit.enabled in %s)", unit.proc.pid,
                        link_cfg.get("url") or link_cfg.get("can"), cfg.source)
        engine = Engine(cfg, link_cfg)
        engine.install_signals()
        try:
            # wait=False: the daemon starts without the unit (READY, watchdog, "waiting for the unit")
            # and the link's reader thread connects when the device appears
            engine.open(wait=False)
            engine.run()
        finally:
            engine.close()
            if unit is not None:
                unit.stop()
    return 0
