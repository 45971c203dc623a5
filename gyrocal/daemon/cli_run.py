"""`gyrocal run`: the calibrator daemon, as systemd starts it.

With no ``--config`` the packaged default runs against the virtual unit (a child `gyrocal sim` on a
pty), so the daemon can be tried on any machine. On a vehicle the service passes
``--config /etc/gyrocal/gyrocal.yaml`` naming the real device.
"""

from __future__ import annotations

import argparse
import logging
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
    with tempfile.TemporaryDirectory(prefix="gyrocal-unit-") as tmp:
        if cfg.virtual_unit["enabled"]:
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
