"""``gyrocal sim``: the virtual strapdown unit on a pty or a python-can bus.

The first line on stdout (flushed) is where the daemon finds the unit: the pty slave path for
``--link pty``, or the bus arguments for ``--link can``. SIGUSR1 power-cycles the unit (a new
session: HELLO, a new bias, seq from 0); SIGUSR2 toggles a silence (the unit stalls: nothing sent,
nothing answered, its counter runs on); SIGHUP replugs the cable (pty: a new pty pair behind the same
``--pty-link``, the unit keeps running); SIGTERM and SIGINT stop it cleanly.

Examples::

    gyrocal sim --rate 200 --pty-link /tmp/gyro0 --status-json /tmp/sim.json
    gyrocal sim --link can --can-interface udp_multicast --can-channel 239.74.163.2 --can-port 43113
    gyrocal sim --duration 60 --record run.csv --seed 3        # run.csv + run.truth.csv
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import signal
import sys
from pathlib import Path
from typing import Any

import numpy as np

from gyrocal.errors import ConfigError
from gyrocal.model.terms import read_terms_file
from gyrocal.protocol import termsets
from gyrocal.sim.autopilot_run import thermal_args
from gyrocal.sim.grades import grade_truth
from gyrocal.sim.recorder import Recorder
from gyrocal.sim.runner import Runner
from gyrocal.sim.schedule import load_schedule, tumble
from gyrocal.sim.truth import EFFECT_FIELDS, NOISE_FIELDS, set_effects, set_noise
from gyrocal.sim.unit import Faults, VirtualUnit

log = logging.getLogger(__name__)

MAX_RATE_HZ = 10_000.0
DEFAULT_CAN_GROUP = "239.74.163.2"  # udp_multicast's IPv4 group when nothing else names a channel


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--link", choices=("pty", "can", "mavlink"), default="pty",
                   help="transport (default pty); mavlink: a virtual PX4 or ArduPilot autopilot")
    p.add_argument("--rate", type=float, default=200.0, metavar="HZ", help="samples per second (default 200)")
    p.add_argument("--seed", type=int, default=0, help="truth seed: same seed, same output (default 0)")
    p.add_argument("--serial", type=int, default=4242, help="unit serial number (default 4242)")
    p.add_argument("--schedule", metavar="FILE.yaml", help="orientation schedule (default: 18-pose tumble)")
    p.add_argument("--duration", type=float, default=0.0, metavar="S",
                   help="stop after S seconds worth of samples (0 = run until SIGTERM)")
    p.add_argument("--power-cycle-every", type=float, default=0.0, metavar="S",
                   help="power-cycle after S seconds of each session (0 = never)")
    p.add_argument("--status-json", metavar="PATH", help="write the unit's status here (atomic, ~1 s)")
    p.add_argument("--noise", action="append", metavar="NAME=VALUE",
                   help=f"sensor noise beyond white, repeatable; NAME one of {', '.join(NOISE_FIELDS)}")
    p.add_argument("--effect", action="append", metavar="NAME=VALUE",
                   help=f"a systematic drift effect, repeatable; NAME one of {', '.join(EFFECT_FIELDS)}")
    p.add_argument("--latitude", type=float, default=None, metavar="DEG",
                   help="the unit turns with the Earth at this latitude (north positive): its gyros read "
                        "15.041 deg/h as true rate, as a real unit's do (default: an Earth that does not "
                        "turn)")
    p.add_argument("--heading", type=float, default=0.0, metavar="DEG",
                   help="with --latitude: the heading of the unit's x axis at switch-on, east of north")
    p.add_argument("--record", metavar="LOG.csv", help="record what was sent (+ LOG.truth.csv)")
    p.add_argument("--flash", metavar="PATH", help="keep boot count and applied set in this JSON file")
    p.add_argument("--pty-link", metavar="PATH", help="symlink PATH to the pty slave (a stable name)")
    # python-can's bus flags, spelled as its own scripts (can.logger, can.player) spell them; what they
    # leave out comes from python-can's config (CAN_INTERFACE/CAN_CHANNEL, /etc/can.conf, ~/.canrc),
    # then udp_multicast on 239.74.163.2. The --can-* spellings are kept for existing scripts.
    from can import VALID_INTERFACES

    b = p.add_argument_group("bus arguments (python-can)")
    b.add_argument("-i", "--interface", "--can-interface", dest="can_interface", default=None,
                   choices=sorted(VALID_INTERFACES), metavar="INTERFACE",
                   help="python-can interface, e.g. socketcan, virtual, udp_multicast (default: python-can's "
                        "config, else udp_multicast)")
    b.add_argument("-c", "--channel", "--can-channel", dest="can_channel", default=None, metavar="CHANNEL",
                   help="CAN channel, e.g. can0, or the multicast group (default: python-can's config, "
                        f"else {DEFAULT_CAN_GROUP})")
    b.add_argument("-b", "--bitrate", type=int, default=None, metavar="BITRATE", help="bitrate of the bus")
    b.add_argument("--bus-kwargs", nargs="+", default=[], metavar="KEY=VALUE",
                   help="more can.Bus keyword arguments, e.g. --bus-kwargs receive_own_messages=True")
    b.add_argument("--can-port", type=int, help="udp_multicast UDP port (default python-can's 43113)")
    b.add_argument("--can-config", metavar="JSON",
                   help="can.Bus keyword arguments as JSON text or a .json file")
    p.add_argument("--dbc", metavar="FILE.dbc", help="CAN database (default: the shipped one)")
    p.add_argument("--can-node-id", type=int, default=0, metavar="N",
                   help="the unit's CAN node id 0..15 (default 0; frame id = DBC id + N)")
    p.add_argument("--grade", choices=("demo", "fibre", "tactical", "consumer"), default="demo",
                   help="unit grade preset: noise, bias instability, temperature sensitivity "
                        "(default demo: the seed-000 unit of the demo; see gyrocal/sim/grades.py)")
    p.add_argument("--terms", action="append", default=[], metavar="NAMES|FILE.yaml",
                   help="a further term set in the unit's table (it NAKs UNKNOWN_TERMS to any other): "
                        "comma-separated names such as 1,gx,gy,gz,dtemp, or a YAML terms file as "
                        "`gyrocal analyze` writes it; repeatable")
    f = p.add_argument_group("fault injection")
    f.add_argument("--nak-next", type=int, default=0, metavar="N", help="NAK the next N coefficient writes")
    f.add_argument("--drop-acks", type=int, default=0, metavar="N", help="ignore the next N writes silently")
    f.add_argument("--never-hello", action="store_true", help="do not send HELLO at switch-on")
    f.add_argument("--garbage-rate", type=float, default=0.0, metavar="P",
                   help="probability per frame of random garbage bytes before it (pty only)")
    f.add_argument("--nan-readback", type=int, default=0, metavar="N",
                   help="answer the next N COEFF_READs with NaN coefficients (valid frame CRC)")
    f.add_argument("--lose-ack", type=int, default=0, metavar="N",
                   help="apply the next N valid writes but lose their ack")
    f.add_argument("--cycle-after-ack", type=int, default=0, metavar="N",
                   help="power-cycle right after each of the next N acks")
    f.add_argument("--no-coeff-read", action="store_true", help="never answer COEFF_READ")
    f.add_argument("--seq-outlier-every", type=float, default=0.0, metavar="S",
                   help="send one sample with a far sequence number every S s (0 = never)")
    f.add_argument("--lose-burst", type=float, default=0.0, metavar="S",
                   help="lose S s of samples on the link in every --lose-every (seq and time run on)")
    f.add_argument("--lose-every", type=float, default=0.0, metavar="S",
                   help="the period of those bursts [s of unit time] (0 = never)")
    f.add_argument("--silence-at", type=float, default=0.0, metavar="S",
                   help="go silent S s after start (see --silence-for; SIGUSR2 toggles at run time)")
    f.add_argument("--silence-for", type=float, default=0.0, metavar="S", help="length of that silence [s]")
    p.add_argument("--log-level", default="WARNING", help="logging level on stderr (default WARNING)")
    p.add_argument("--parent-pid", type=int, default=None, metavar="PID",
                   help="stop when process PID (the daemon that started this unit) dies, even by SIGKILL")
    from gyrocal.sim.autopilot_run import configure as configure_autopilot

    configure_autopilot(p)


def can_bus_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The ``can.Bus`` keyword arguments from ``--can-config`` or the ``--can-*`` options."""
    if args.can_config:
        text = args.can_config
        where = "--can-config"
        if not text.lstrip().startswith("{"):
            where = text
            try:
                text = Path(text).read_text(encoding="utf-8")
            except OSError as err:
                raise ConfigError(f"--can-config {where}: cannot read it ({err.strerror})") from err
        try:
            kw = json.loads(text)
        except json.JSONDecodeError as err:
            raise ConfigError(f"{where}: not valid JSON ({err.msg} at line {err.lineno} column {err.colno}); "
                              'write e.g. {"interface": "virtual", "channel": "gyro"}') from err
        if not isinstance(kw, dict) or "interface" not in kw:
            raise ConfigError(f'{where}: must be a JSON object with an "interface" field')
        return kw
    from can.util import cast_from_string

    from gyrocal.drivers.can_defaults import with_python_can_defaults

    kw: dict[str, Any] = {k: v for k, v in (("interface", args.can_interface), ("channel", args.can_channel),
                                            ("bitrate", args.bitrate)) if v is not None}
    kw = with_python_can_defaults(kw, "gyrocal sim")
    if not kw.get("interface"):
        kw["interface"] = "udp_multicast"
    if kw.get("channel") is None and kw["interface"] == "udp_multicast":
        kw["channel"] = DEFAULT_CAN_GROUP
    if args.can_port is not None:
        kw["port"] = args.can_port
    for item in args.bus_kwargs:  # as can.logger's --bus-kwargs: KEY=VALUE, values cast as python-can does
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--bus-kwargs {item!r}: write KEY=VALUE, e.g. receive_own_messages=True")
        kw[key] = cast_from_string(value)
    return kw


def _check(args: argparse.Namespace) -> None:
    if not 0 < args.rate <= MAX_RATE_HZ:
        raise ConfigError(f"--rate {args.rate:g}: must be in (0, {MAX_RATE_HZ:g}] samples/s")
    for name in ("duration", "power_cycle_every", "seq_outlier_every", "silence_at", "silence_for",
                 "lose_burst", "lose_every", "nak_next", "drop_acks", "nan_readback", "lose_ack",
                 "cycle_after_ack"):
        if getattr(args, name) < 0:
            raise ConfigError(f"--{name.replace('_', '-')}: must be >= 0")
    if args.lose_burst > 0 and not args.lose_every > args.lose_burst:
        raise ConfigError(f"--lose-burst {args.lose_burst:g}: give --lose-every S, longer than the burst")
    if not 0.0 <= args.garbage_rate <= 1.0:
        raise ConfigError(f"--garbage-rate {args.garbage_rate:g}: must be a probability in [0, 1]")
    if args.latitude is not None and not -90.0 <= args.latitude <= 90.0:
        raise ConfigError(f"--latitude {args.latitude:g}: write a latitude in degrees, -90 to 90")
    if args.latitude is not None and args.link == "mavlink":
        raise ConfigError("--latitude: the virtual autopilot's Earth does not turn; use it with --link pty "
                          "or can")
    if args.link == "can" and args.pty_link:
        raise ConfigError("--pty-link only applies to --link pty")
    if not 0 <= args.can_node_id <= 15:
        raise ConfigError(f"--can-node-id {args.can_node_id}: must be a CAN node id 0 to 15")


def _register_terms(specs: list[str]) -> None:
    """Add ``--terms`` sets to the unit's table (the protocol's registry in this process)."""
    for spec in specs:
        path = Path(spec)
        try:
            if path.suffix in (".yaml", ".yml") or path.exists():
                names = read_terms_file(path)
            else:
                names = [n.strip() for n in spec.split(",")]
            termsets.register_unit_terms(names)
        except ConfigError as err:
            raise ConfigError(f"--terms {spec}: {err}") from None


def _load_flash(unit: VirtualUnit, path: str | None) -> None:
    if not path or not Path(path).exists():
        return
    try:
        unit.load_flash(json.loads(Path(path).read_text(encoding="utf-8")))
    except (OSError, ValueError, KeyError, TypeError) as err:
        msg = f"--flash {path}: cannot read the unit's flash state ({err}); delete the file"
        raise ConfigError(msg) from err


def _die_with_parent(parent_pid: int) -> None:
    """SIGTERM to this unit when its parent dies, even by SIGKILL (Linux prctl PR_SET_PDEATHSIG), so
    a daemon that was killed leaves no orphan unit on the pty (an operator's audit). Set in the child
    itself: a preexec_fn is unsafe in a process with threads. A parent that died before the call is
    seen by getppid."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM), 0, 0, 0)  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the service manager's cgroup still stops it
        return
    if os.getppid() != parent_pid:
        raise SystemExit(0)


def main(args: argparse.Namespace) -> int:
    if args.parent_pid is not None:
        _die_with_parent(args.parent_pid)
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
                        format="gyrocal sim: %(levelname)s %(message)s")
    if logging.getLogger().level > logging.INFO:  # a bus that failed to open warns again from __del__
        logging.getLogger("can").setLevel(logging.ERROR)
    _check(args)
    _register_terms(args.terms)
    if args.link == "mavlink":
        from gyrocal.sim.autopilot_run import main as autopilot_main

        return autopilot_main(args)
    schedule = load_schedule(args.schedule) if args.schedule else tumble()
    faults = Faults(nak_next=args.nak_next, drop_acks=args.drop_acks, never_hello=args.never_hello,
                    garbage_rate=args.garbage_rate, nan_readback=args.nan_readback, lose_ack=args.lose_ack,
                    cycle_after_ack=args.cycle_after_ack, no_coeff_read=args.no_coeff_read,
                    seq_outlier_every_s=args.seq_outlier_every, silence_at_s=args.silence_at,
                    silence_for_s=args.silence_for, lose_burst_s=args.lose_burst,
                    lose_every_s=args.lose_every)
    truth = set_noise(grade_truth(args.grade, args.rate), args.noise)  # a grade, then --noise on top
    truth = set_effects(truth, args.effect)
    if args.latitude is not None:
        truth = dataclasses.replace(truth, latitude_deg=args.latitude, heading_deg=args.heading)
    # the temperature course (an outside check found them silently ignored here: every switch-on warmed
    # alike, so T, dT/dt and a warm-up could not be told apart in a recording)
    ambients, rise, tau = thermal_args(args)
    th = truth.thermal
    truth = dataclasses.replace(truth, thermal=dataclasses.replace(
        th, rise_c=th.rise_c if rise is None else rise, tau_s=th.tau_s if tau is None else tau))
    unit = VirtualUnit(truth, schedule, args.rate, args.seed, args.serial, faults=faults, ambients_c=ambients)
    _load_flash(unit, args.flash)
    transport = _open_transport(args)
    recorder = None
    try:
        if args.record:
            meta = {"source": "gyrocal sim", "serial": args.serial, "seed": args.seed, "rate_hz": args.rate,
                    "sensor": "virtual strapdown unit", "t_origin": "switch_on"}
            try:
                recorder = Recorder(args.record, meta)
            except OSError as err:
                raise ConfigError(f"--record {args.record}: cannot write ({err.strerror})") from err
        runner = Runner(unit, transport, duration_s=args.duration, status_path=args.status_json,
                        power_cycle_every_s=args.power_cycle_every, recorder=recorder,
                        info={"seed": args.seed}, flash_path=args.flash)
        _install_signals(runner)  # before the address goes out: a caller may signal at once
        print(transport.describe(), flush=True)
        runner.run()
    finally:
        transport.close()
        if recorder is not None:
            recorder.close()
    return 0


def _open_transport(args: argparse.Namespace) -> Any:
    from gyrocal.sim.transports import CanTransport, PtyTransport

    if args.link == "pty":
        return PtyTransport(args.pty_link, garbage_rate=args.garbage_rate,
                            rng=np.random.default_rng([args.seed, 0x6A7B]))
    return CanTransport(can_bus_kwargs(args), dbc_path=args.dbc, node_id=args.can_node_id)


def _install_signals(runner: Runner) -> None:
    def stop(signum: int, frame: object) -> None:
        runner.request_stop()

    def cycle(signum: int, frame: object) -> None:
        runner.request_power_cycle()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    if hasattr(signal, "SIGUSR1"):
        signal.signal(signal.SIGUSR1, cycle)
        signal.signal(signal.SIGUSR2, lambda signum, frame: runner.toggle_silence())
        signal.signal(signal.SIGHUP, lambda signum, frame: runner.request_replug())


if __name__ == "__main__":
    from gyrocal.cli import main as cli_main

    sys.exit(cli_main(["sim", *sys.argv[1:]]))
