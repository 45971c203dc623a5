"""``gyrocal replay LOG``: run the daemon's engine on a recording, or play it into a pty (``--pty``).

Off line (default) the daemon's Engine runs on the recording's unit time at full speed, and the
result says what the daemon would have done: sessions, validations, pushes (coefficients
recorded, never sent) and each state change. The same log gives the same decisions every run.
A push is decided on the data as the daemon sees it: after it, the recording's output is
re-compensated with the pushed set, as the unit would have applied it (gyrocal/replay/unit.py).

LOG is any format of docs/logformat.md: a python-can log or a serial capture of the link (with
the unit's HELLO and COEFF_REPORT), or a sample log (CSV, .ulg, .bin, .tlog, rosbag2), whose sessions
each get a HELLO and whose unit is taken to hold no calibration.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from gyrocal.daemon.config import load_config
from gyrocal.errors import ConfigError
from gyrocal.readers import add_arguments, options_from_args
from gyrocal.replay.source import open_recording


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="LOG",
                        help="a recording: .asc/.blf/.log, .cap, CSV, .ulg, .bin, .tlog, rosbag2 "
                             "(docs/logformat.md)")
    parser.add_argument("--config", metavar="FILE.yaml",
                        help="daemon config whose estimator/validation/push/still settings to use "
                             "(default: the shipped one)")
    parser.add_argument("--state-dir", metavar="DIR",
                        help="calibration store to start from and write to (default: a fresh temporary "
                             "one, so a replay never touches a daemon's store)")
    parser.add_argument("--json", metavar="OUT.json", help="write the summary here ('-' = stdout)")
    parser.add_argument("--chunk-s", type=float, default=1.0, metavar="S",
                        help="recording time fed per engine round, off line (default 1 s): decisions are "
                             "taken at these boundaries")
    parser.add_argument("--pty", action="store_true",
                        help="play the log into a pty in real time for a live daemon (prints the path)")
    parser.add_argument("--pty-link", metavar="PATH", help="with --pty: also symlink PATH to the pty")
    parser.add_argument("--bus", metavar="JSON",
                        help="play the log onto a python-can bus in real time instead, e.g. "
                             '\'{"interface": "socketcan", "channel": "vcan0"}\' (can.Bus arguments)')
    parser.add_argument("--speed", type=float, default=1.0, help="with --pty/--bus: x real time (default 1)")
    add_arguments(parser)


def main(args: argparse.Namespace) -> int:
    if args.chunk_s <= 0 or args.speed <= 0:
        raise ConfigError("--chunk-s and --speed must be > 0")
    rec = open_recording(args.log, args.format, options_from_args(args))
    for w in rec.warnings:  # a streamed CSV's come after the replay
        print(f"gyrocal: warning: {w}", file=sys.stderr)
    shown = len(rec.warnings)
    if args.pty or args.bus:
        from gyrocal.replay.pty_player import play_bus, play_pty

        def say(where: str) -> None:
            print(where, flush=True)

        if args.bus:
            try:
                bus = json.loads(args.bus)
            except json.JSONDecodeError as err:
                raise ConfigError(f"--bus: not JSON ({err.msg}); give can.Bus arguments, "
                                  '\'{"interface": "socketcan", "channel": "vcan0"}\'') from None
            res = play_bus(rec, bus, args.speed, announce=say, dbc_path=args.dbc)
        else:
            res = play_pty(rec, args.pty_link, args.speed, announce=say)
        _emit(args, res, f"{res['samples_sent']} samples played into {res['target']}; "
                         f"{len(res['pushes'])} push(es) recorded")
        return 0
    from gyrocal.replay.run import replay

    with tempfile.TemporaryDirectory(prefix="gyrocal-replay-") as tmp:
        state = args.state_dir or str(Path(tmp) / "state")
        Path(state).mkdir(parents=True, exist_ok=True)
        cfg = load_config(args.config, {"state_dir": state, "control_socket": str(Path(tmp) / "control.sock"),
                                        "watchdog": False})
        res = replay(rec, cfg, args.chunk_s)
    for w in rec.warnings[shown:]:
        print(f"gyrocal: warning: {w}", file=sys.stderr)
    if res["samples"] == 0:
        why = ", ".join(f"{v} {k}" for k, v in res["dropped"].items()) or "it holds none"
        raise ConfigError(f"{args.log}: no sample to replay ({why}); is it the format its extension "
                          "says? (--format, docs/logformat.md)")
    _emit(args, res, _text(res))
    return 0


def _emit(args: argparse.Namespace, res: dict, text: str) -> None:
    if args.json == "-":
        print(json.dumps(res, indent=1))
        return
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
    print(text)


def _text(res: dict) -> str:
    dropped = ", ".join(f"{v} {k}" for k, v in res["dropped"].items()) or "none"
    lines = [f"{res['recording']}: {res['samples']} samples, {res['replayed_s']:.1f} s replayed in "
             f"{res['wall_s']:.2f} s ({res['samples_per_s'] or 0:.0f} samples/s); dropped: {dropped}"]
    for s in res["sessions"]:
        u = s["unit"]
        lines.append(f"session {s['index']}: unit {u['serial']} boot {u['boot_count']}: "
                     f"{s['samples']} samples, "
                     f"{s['still_samples']} still, {s['trained_samples']} trained; ends {s['final_state']} "
                     f"({s['reason']})")
    for v in res["validations"]:
        lines.append(f"validation at {v['t_s']:.1f} s: {'passed' if v['passed'] else 'failed'} "
                     f"(held-out rms {_rms(v['rms_current_dps'])} -> {_rms(v['rms_new_dps'])} deg/s)")
    for p in res["pushes"]:
        rows = p["coefficients_dps"]
        bias = ", ".join(f"{r[0] * 3600:.2f}" for r in rows) if rows and rows[0] else "-"
        lines.append(f"push v{p['version']} at {p['unit_time_s']:.1f} s unit time: {p['status']} "
                     f"(engine: {p['engine_result']}); bias x,y,z [deg/h]: {bias}")
    if not res["pushes"]:
        lines.append("no push decided")
    return "\n".join(lines)


def _rms(d: dict) -> str:
    return "%.3g" % (sum(v * v for v in d.values()) ** 0.5)
