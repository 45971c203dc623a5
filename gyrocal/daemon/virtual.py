"""Start the virtual strapdown unit as a child process, for the embedded default and the demo.

The virtual unit is a separate process (`gyrocal sim`) talking over a real pty pair or a real
python-can bus, exactly as hardware would: the daemon cannot tell the difference, so the demo
exercises the same code paths as a vehicle.
"""

from __future__ import annotations

import json
import os
import random
import select
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from gyrocal.errors import LinkError
from gyrocal.sim.schedule import tumble


@dataclass
class VirtualUnitProcess:
    """A running `gyrocal sim` child, the link config that reaches it, and its status file."""

    proc: subprocess.Popen[str]
    link_cfg: dict[str, Any]
    status_path: Path

    def status(self) -> dict[str, Any]:
        """The unit's own truth-based status (drift RMS before/after compensation), or {}."""
        try:
            return json.loads(self.status_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}

    def power_cycle(self) -> None:
        """Switch the unit off and on again (SIGUSR1): a new bias and a new HELLO."""
        import signal

        self.proc.send_signal(signal.SIGUSR1)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def free_udp_port() -> int:
    """A port for udp_multicast unlikely to collide with another run on the same machine."""
    return 20000 + (os.getpid() * 7919 + random.randrange(1000)) % 40000


def start_virtual_unit(
    vcfg: dict[str, Any], kind: str, workdir: Path, extra: list[str] | None = None,
    can_port: int | None = None,
) -> VirtualUnitProcess:
    """Spawn `gyrocal sim` for the ``virtual_unit`` config section on a pty or a CAN bus."""
    workdir.mkdir(parents=True, exist_ok=True)
    status_path = workdir / "unit-status.json"
    if vcfg.get("schedule"):
        schedule_path = Path(vcfg["schedule"])
    else:
        sched = tumble(float(vcfg["dwell_s"]), float(vcfg["move_s"]))
        schedule_path = workdir / "schedule.yaml"
        schedule_path.write_text(yaml.safe_dump({
            "dwell_s": sched.dwell_s, "move_s": sched.move_s, "poses": sched.poses_g.tolist()}))
    cmd = [sys.executable, "-m", "gyrocal.cli", "sim", "--seed", str(vcfg["seed"]),
           "--rate", str(vcfg["rate_hz"]), "--schedule", str(schedule_path),
           "--status-json", str(status_path), "--parent-pid", str(os.getpid())]
    if kind == "can":
        port = can_port or free_udp_port()
        channel = "239.74.163.2"
        cmd += ["--link", "can", "--can-interface", "udp_multicast", "--can-channel", channel,
                "--can-port", str(port)]
        link_cfg = {"kind": "can", "can": {"interface": "udp_multicast", "channel": channel, "port": port}}
    else:
        cmd += ["--link", "pty", "--pty-link", str(workdir / "unit.pty")]
        link_cfg = {"kind": "serial"}
    cmd += list(vcfg.get("extra_args") or []) + list(extra or [])
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=None, text=True)
    if kind == "can":
        vu = VirtualUnitProcess(proc, link_cfg, status_path)
        _wait_started(vu, workdir)
        return vu
    line = _read_line(proc, 15.0)
    path = line.strip().split()[-1] if line.strip() else ""
    if not path.startswith("/"):
        proc.kill()
        raise LinkError(f"the virtual unit did not print its pty path (got {line!r})")
    link_cfg.update({"url": path, "baudrate": 921600})
    return VirtualUnitProcess(proc, link_cfg, status_path)


def _read_line(proc: subprocess.Popen[str], timeout_s: float) -> str:
    if proc.stdout is None:
        return ""
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    return proc.stdout.readline() if ready else ""


def _wait_started(vu: VirtualUnitProcess, workdir: Path, timeout_s: float = 15.0) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if vu.proc.poll() is not None:
            raise LinkError(f"the virtual unit exited at start (status {vu.proc.returncode})")
        if vu.status_path.exists():
            return
        time.sleep(0.05)
