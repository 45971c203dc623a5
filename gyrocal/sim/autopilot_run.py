"""``gyrocal sim --link mavlink --autopilot px4|ardupilot``: the virtual autopilot on a pty or UDP.

The first stdout line says where to connect, in pymavlink's connection-string syntax: the pty slave
path (open it with any baud rate), or ``udpin:127.0.0.1:PORT`` when ``--mavlink-udp 127.0.0.1:PORT``
was given (the autopilot sends there from its own port, as PX4 SITL sends to 14550, and answers the
address that talks back). Paced in real time. A reboot (MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, SIGUSR1
or an injected fault) goes silent for ``REBOOT_S`` and starts a new boot: time from 0, a new bias.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import select
import signal
import socket
import time
import tty
from pathlib import Path
from typing import Any

from gyrocal.errors import ConfigError
from gyrocal.sim.autopilot import AutopilotFaults, VirtualAutopilot
from gyrocal.sim.runner import write_json_atomic
from gyrocal.sim.truth import Thermal

log = logging.getLogger(__name__)

REBOOT_S = 1.5
"""How long a rebooting autopilot stays silent [s] (a bootloader and sensor start-up)."""


class RawPty:
    """The autopilot's end of a pty pair, carrying raw bytes (non-blocking; a full pty drops bytes)."""

    def __init__(self, link_path: str | None = None) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self.link_path = link_path
        if link_path:
            p = Path(link_path)
            if p.is_symlink():
                p.unlink()
            p.symlink_to(self.path)
        self.dropped = 0

    def describe(self) -> str:
        return self.path

    def write(self, data: bytes) -> None:
        try:
            os.write(self._master, data)
        except BlockingIOError:
            self.dropped += len(data)
        except OSError:
            self.dropped += len(data)

    def read(self, timeout_s: float) -> bytes:
        r, _, _ = select.select([self._master], [], [], max(timeout_s, 0.0))
        if not r:
            return b""
        try:
            return os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        if self.link_path and Path(self.link_path).is_symlink():
            Path(self.link_path).unlink()


class Udp:
    """Send to HOST:PORT from an ephemeral port and answer whoever talks back (like SITL's udpout)."""

    def __init__(self, host: str, port: int) -> None:
        self.dest = (host, port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1" if host in ("127.0.0.1", "localhost") else "", 0))
        self.sock.setblocking(False)

    def describe(self) -> str:
        return f"udpin:{self.dest[0]}:{self.dest[1]}"

    def write(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.dest)
        except OSError:
            pass  # nobody listens yet: a UDP autopilot sends into the void

    def read(self, timeout_s: float) -> bytes:
        r, _, _ = select.select([self.sock], [], [], max(timeout_s, 0.0))
        if not r:
            return b""
        try:
            data, addr = self.sock.recvfrom(65536)
        except OSError:
            return b""
        self.dest = addr
        return data

    def close(self) -> None:
        self.sock.close()


class AutopilotRunner:
    """Pace the virtual autopilot in real time over a transport."""

    def __init__(
        self,
        ap: VirtualAutopilot,
        transport: Any,
        *,
        duration_s: float = 0.0,
        status_path: str | None = None,
        flash_path: str | None = None,
    ) -> None:
        self.ap, self.tr = ap, transport
        self.duration_s = duration_s
        self.status_path, self.flash_path = status_path, flash_path
        self._stop = False
        self._cycle = False
        self._t0 = 0.0
        self._silent_until = 0.0  # a reboot's silence [monotonic s]: a new boot follows
        self._mute_until = 0.0  # a hang's [monotonic s]: the same boot goes on
        self.bytes_sent = 0

    def request_stop(self) -> None:
        self._stop = True

    def request_power_cycle(self) -> None:
        self._cycle = True

    def _boot(self, now: float) -> None:
        self.ap.power_on(time.time())
        self._t0 = now
        self._save_flash()

    def run(self) -> None:
        start = time.monotonic()
        self._boot(start)
        next_status = start
        while not self._stop:
            now = time.monotonic()
            if self.duration_s and now - start >= self.duration_s:
                break
            if self._cycle or self.ap.reboot_pending:
                self._cycle = False
                self.ap.reboot_pending = False
                self._save_flash()
                self._silent_until = now + REBOOT_S
            if self.ap.silence_pending:  # hung, not rebooting: the same boot goes on after it
                self.ap.silence_pending = False
                self._mute_until = now + self.ap.faults.silence_s
            if self._silent_until or self._mute_until:
                if now < max(self._silent_until, self._mute_until):
                    self.tr.read(0.01)  # a booting or hung autopilot hears nothing
                    continue
                if self._silent_until:
                    self._boot(now)
                self._silent_until = self._mute_until = 0.0
            self._send(self.ap.render(now - self._t0))
            data = self.tr.read(0.004)
            if data:
                for m in self.ap.mav.parse_buffer(data) or []:
                    self._send(self.ap.handle(m, time.monotonic() - self._t0))
            if self.status_path and now >= next_status:
                next_status = now + 0.5
                write_json_atomic(self.status_path, self.ap.status())
        self._save_flash()
        if self.status_path:
            write_json_atomic(self.status_path, self.ap.status())

    def _send(self, msgs: list[Any]) -> None:
        if not msgs:
            return
        buf = b"".join(m.pack(self.ap.mav) for m in msgs)
        self.bytes_sent += len(buf)
        self.tr.write(buf)

    def _save_flash(self) -> None:
        if self.flash_path:
            write_json_atomic(self.flash_path, self.ap.flash_state())


def configure(p: argparse.ArgumentParser) -> None:
    """The flags ``gyrocal sim`` adds for ``--link mavlink`` (the rest are shared)."""
    g = p.add_argument_group("virtual autopilot (--link mavlink)")
    g.add_argument(
        "--autopilot", choices=("px4", "ardupilot"), default="px4", help="which autopilot (default px4)"
    )
    g.add_argument(
        "--mavlink-udp", metavar="HOST:PORT", help="send MAVLink over UDP to HOST:PORT instead of a pty"
    )
    g.add_argument(
        "--warmup-tau",
        type=float,
        default=None,
        metavar="S",
        help="warm-up time constant [s] of the temperature's rise (default: 120 for an autopilot, the "
        "grade's for a unit)",
    )
    g.add_argument(
        "--ambient",
        default="",
        metavar="C[,C...]",
        help="the temperature at each switch-on of this run [degC], in order, the last repeating "
        "(default: 20 for an autopilot, 25 for a unit); each warm-up rises --rise degC from it",
    )
    g.add_argument(
        "--rise",
        type=float,
        default=None,
        metavar="C",
        help="the warm-up's rise [degC] (default: 30 for an autopilot, the grade's for a unit; 0: held at "
        "its ambient from switch-on, as an IMU heater holds its set point)",
    )
    g.add_argument(
        "--rotation",
        type=int,
        default=None,
        metavar="N",
        help="board rotation (PX4 SENS_BOARD_ROT / ArduPilot AHRS_ORIENTATION enum, 0..37, 39, 40): "
        "offsets apply in the sensor frame, the output is rotated to body (default: 0, or the --flash value)",
    )
    g.add_argument(
        "--drop-param-values",
        type=int,
        default=0,
        metavar="N",
        help="fault: drop the PARAM_VALUE echo of the next N PARAM_SETs",
    )
    g.add_argument(
        "--reject-param", default="", metavar="NAME", help="fault: refuse writes of NAME (echo differs)"
    )
    g.add_argument(
        "--reboot-after-sets",
        type=int,
        default=0,
        metavar="N",
        help="fault: reboot after the N-th PARAM_SET of a boot",
    )
    g.add_argument(
        "--silence-after-sets",
        type=int,
        default=0,
        metavar="N",
        help="fault: hang after the N-th PARAM_SET of a boot, unanswered, for --silence-for s (default 5), "
        "then go on in the same boot",
    )
    g.add_argument(
        "--mute-params-after-sets",
        type=int,
        default=0,
        metavar="N",
        help="fault: after the N-th PARAM_SET of a boot, apply writes but send no PARAM_VALUE for "
        "--silence-for s (default 5); the stream and heartbeats go on",
    )
    g.add_argument(
        "--no-imu-temperature",
        action="store_true",
        help="fault: send every IMU temperature as 0 (MAVLink's 'not provided')",
    )


def thermal_args(args: argparse.Namespace) -> tuple[tuple[float, ...], float | None, float | None]:
    """``--ambient`` [degC per switch-on], ``--rise`` [degC] and ``--warmup-tau`` [s], checked (None:
    not given, the link's own default). Raises ConfigError naming the option."""
    if args.warmup_tau is not None and not (math.isfinite(args.warmup_tau) and args.warmup_tau > 0):
        raise ConfigError("--warmup-tau must be > 0 s")
    if args.rise is not None and not (math.isfinite(args.rise) and args.rise >= 0):
        raise ConfigError("--rise must be a finite number of degC >= 0")
    try:
        ambients = tuple(float(a) for a in args.ambient.split(",") if a.strip())
    except ValueError as err:
        raise ConfigError(
            f"--ambient {args.ambient!r}: write degC values separated by commas, e.g. 20,30"
        ) from err
    if not all(math.isfinite(a) for a in ambients):
        raise ConfigError(f"--ambient {args.ambient!r}: give finite degC values")
    return ambients, args.rise, args.warmup_tau


def main(args: argparse.Namespace) -> int:
    faults = AutopilotFaults(args.drop_param_values, args.reject_param, args.reboot_after_sets,
                             args.silence_after_sets, args.silence_for or 5.0, args.no_imu_temperature,
                             args.mute_params_after_sets)
    ambients, rise, tau = thermal_args(args)
    ap = VirtualAutopilot(
        args.autopilot,
        args.rate,
        args.seed,
        faults=faults,
        thermal=Thermal(ambient_c=20.0, rise_c=30.0 if rise is None else rise,
                        tau_s=120.0 if tau is None else tau),
        ambients_c=ambients,
    )
    if args.flash and Path(args.flash).exists():
        try:
            ap.load_flash(json.loads(Path(args.flash).read_text(encoding="utf-8")))
        except (OSError, ValueError) as err:
            raise ConfigError(f"--flash {args.flash}: unreadable ({err}); delete the file") from err
    if args.rotation is not None:
        from gyrocal.sim.board_rotation import SUPPORTED

        if args.rotation not in SUPPORTED:
            raise ConfigError(f"--rotation {args.rotation}: the virtual autopilot models {SUPPORTED}")
        ap.params[ap.rotation_param] = float(args.rotation)
    if args.mavlink_udp:
        host, _, port = args.mavlink_udp.rpartition(":")
        if not port.isdigit():
            raise ConfigError(f"--mavlink-udp {args.mavlink_udp!r}: write HOST:PORT, e.g. 127.0.0.1:14550")
        transport: Any = Udp(host or "127.0.0.1", int(port))
    else:
        transport = RawPty(args.pty_link)
    runner = AutopilotRunner(
        ap, transport, duration_s=args.duration, status_path=args.status_json, flash_path=args.flash
    )
    signal.signal(signal.SIGTERM, lambda *_: runner.request_stop())
    signal.signal(signal.SIGINT, lambda *_: runner.request_stop())
    signal.signal(signal.SIGUSR1, lambda *_: runner.request_power_cycle())
    print(transport.describe(), flush=True)
    try:
        runner.run()
    finally:
        transport.close()
    return 0
