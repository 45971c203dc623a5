"""Benchmark: the real daemon (``gyrocal run``, link kind mavlink) calibrates virtual autopilots.

The error is computed by gyrocal/sim/autopilot_truth.py (the same as ``gyrocal demo --mavlink``).
For each autopilot (PX4, ArduPilot): start ``gyrocal sim --link mavlink`` on a pty (a board warming
from 20 to 50 degC), run the daemon with the temperature polynomial as its model through the warm-up
(4 time constants, at least until its first push; it pushes again when a wider range improves the
set), stop both, and compare the gyro offset error over the temperature range of the set the
autopilot holds at the end (its TMIN..TMAX), before and after, in deg/h:

    error(T) = true raw offset(T) - what the autopilot subtracts at T with its parameters

"before" uses the parameters the autopilot booted with, "after" those it holds at the end (read from
the simulator's flash file), both at the learning boot's bias. The autopilot's subtraction is
evaluated continuously (gyrocal.mavlink.profiles: applied + clamp_adjust); PX4's 1 degC staircase
adds at most slope x 1 degC on top, reported as ``px4_staircase_dph``. For PX4, whose TC_G_ENABLE
was 0 at boot, the set applies after the next reboot (a new switch-on bias then adds a constant);
``shape_after_dph`` is the error with its mean over the range removed, the part a reboot keeps.

``seen`` gives the same figures over the whole range the warm-up covered (TMIN of the held set, the
coldest still temperature, to the board's temperature at the end of the run): above the held TMAX the
autopilot clamps, and that error is in these figures.

    python benchmarks/bench_mavlink.py --quick --json out/bench_mavlink.json
    python benchmarks/bench_mavlink.py --quick --autopilot px4 --rotation 2   # a board mounted yaw 90

``--rotation N`` starts the virtual autopilot with that board rotation (PX4 SENS_BOARD_ROT, ArduPilot
AHRS_ORIENTATION): it subtracts its offsets in the sensor frame and rotates its output to the body
frame; the truth is rotated by the simulator's own rotation (gyrocal/sim/board_rotation.py), so a
wrong transform in the link shows as a wrong calibration. Figures are per body axis.

``--ambients 20,30`` runs two warm-ups, 20 -> 50 and 30 -> 60 degC, the autopilot power-cycled in
between (a hotter day): the range held at the end is the merge of both (docs/mavlink.md), and the
figures are those of the last boot, at its own switch-on bias.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from gyrocal.mavlink.profiles import PROFILES
from gyrocal.sim.autopilot_truth import offset_errors

DPH = 3600.0
TERMS = ["1", "temp", "temp^2"]
"""The daemon's model: a quadratic in temperature (docs/mavlink.md: the cubic term is not determined
by the daemon's rank test over a 30 degC warm-up)."""


def run_one(kind: str, tau_s: float, limit_s: float, seed: int, work: Path,
            ambients: tuple[float, ...] = (), rotation: int = 0) -> dict[str, Any]:
    """One daemon against one virtual autopilot; with ``ambients`` of several values, one warm-up per
    value, the autopilot power-cycled (SIGUSR1) after each but the last. ``rotation``: its board
    rotation (SENS_BOARD_ROT / AHRS_ORIENTATION)."""
    work.mkdir(parents=True, exist_ok=True)
    boots = max(1, len(ambients))
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    sim = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "gyrocal.cli",
            "sim",
            "--link",
            "mavlink",
            "--autopilot",
            kind,
            "--rate",
            "250",
            "--seed",
            str(seed),
            "--warmup-tau",
            str(tau_s),
            "--rotation",
            str(rotation),
            "--flash",
            str(work / "flash.json"),
            "--status-json",
            str(work / "ap.json"),
            *(["--ambient", ",".join(f"{a:g}" for a in ambients)] if ambients else []),
        ],
        stdout=subprocess.PIPE,
        stderr=(work / "sim.err").open("wb"),
        env=env,
    )
    pty = sim.stdout.readline().decode().strip()  # type: ignore[union-attr]
    cfg = {
        "link": {"kind": "mavlink", "url": pty, "mavlink": {"autopilot": kind}},
        "virtual_unit": {"enabled": False},
        "estimator": {"terms": TERMS},
        "state_dir": str(work / "state"),
        "control_socket": str(work / "ctl.sock"),
        "watchdog": False,
    }
    (work / "cfg.json").write_text(json.dumps(cfg))
    (work / "cfg.yaml").write_text(json.dumps(cfg))  # JSON is YAML
    t0 = time.monotonic()
    daemon = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "gyrocal.cli",
            "run",
            "--config",
            str(work / "cfg.yaml"),
            "--log-level",
            "INFO",
        ],
        stdout=(work / "run.log").open("wb"),
        stderr=subprocess.STDOUT,
        env=env,
    )
    status: dict[str, Any] = {}
    pushed_after = None
    pushes: list[dict[str, Any]] = []
    boot, boot_t0 = 1, t0
    try:
        # run through the warm-up (4 time constants: 98 % of the 30 degC rise): the daemon keeps
        # validating while it monitors and pushes again when a wider range improves the set
        while time.monotonic() - boot_t0 < limit_s:
            time.sleep(2.0)
            out = subprocess.run(
                [sys.executable, "-m", "gyrocal.cli", "status", "--socket", str(work / "ctl.sock"), "--json"],
                capture_output=True,
                text=True,
                env=env,
            )
            if out.returncode == 0 and out.stdout.strip():
                status = json.loads(out.stdout)
                last = status.get("last_push") or {}
                if last.get("status") == "acked" and (
                    not pushes or pushes[-1]["version"] != last.get("version")
                ):
                    pushes.append({"version": last.get("version"), "boot": boot,
                                   "at_s": round(time.monotonic() - boot_t0, 1)})
                    pushed_after = pushed_after or time.monotonic() - t0
            if pushed_after and time.monotonic() - boot_t0 > 4.0 * tau_s:
                if boot >= boots:
                    break
                sim.send_signal(signal.SIGUSR1)  # switch the autopilot off and on: the next warm-up
                boot, boot_t0 = boot + 1, time.monotonic()
    finally:
        for proc in (daemon, sim):
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return {
        "status": status,
        "pushed_after_s": pushed_after,
        "pushes": pushes,
        "boots": boot,
        "flash": json.loads((work / "flash.json").read_text()),
        "end_temp_c": json.loads((work / "ap.json").read_text()).get("temp_c"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fast warm-up (tau 25 s), 180 s limit per autopilot")
    ap.add_argument("--autopilot", choices=("px4", "ardupilot", "both"), default="both")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--rotation",
        type=int,
        default=0,
        metavar="N",
        help="board rotation of the virtual autopilot (SENS_BOARD_ROT / AHRS_ORIENTATION enum; "
        "e.g. 2 = yaw 90, 8 = roll 180); the figures are per body axis",
    )
    ap.add_argument("--json", metavar="OUT.json")
    ap.add_argument("--ambients", default="", metavar="C,C,...",
                    help="one warm-up per value, each from that board temperature [degC] (+30 degC), the "
                    "autopilot power-cycled in between; figures at the last boot over the merged range")
    args = ap.parse_args(argv)
    ambients = tuple(float(a) for a in args.ambients.split(",") if a.strip())
    tau, limit = (25.0, 180.0) if args.quick else (60.0, 420.0)
    kinds = ("px4", "ardupilot") if args.autopilot == "both" else (args.autopilot,)
    results: dict[str, Any] = {
        "quick": args.quick,
        "warmup_tau_s": tau,
        "terms": TERMS,
        "seed": args.seed,
        "rotation": args.rotation,
        "ambients_c": list(ambients),
    }
    with tempfile.TemporaryDirectory(prefix="bench_mavlink_") as tmp_dir:
        tmp = os.environ.get("BENCH_MAVLINK_KEEP") or tmp_dir
        for kind in kinds:
            r = run_one(kind, tau, limit, args.seed, Path(tmp) / kind, ambients, args.rotation)
            at = {"boot": r["boots"], "ambients_c": ambients}
            params = r["flash"]["params"]
            prof = PROFILES[kind](0)
            lo, hi = params[prof.p_tmin], params[prof.p_tmax]  # type: ignore[attr-defined]
            if not r["pushed_after_s"]:
                results[kind] = {"pushed": False, "reason": (r["status"] or {}).get("reason")}
                print(f"{kind}: no push within {limit:.0f} s: {results[kind]['reason']}")
                continue
            temps = np.linspace(lo, hi, 5)
            res = {
                "pushed": True,
                "pushed_after_s": round(r["pushed_after_s"], 1),
                "pushes": r["pushes"],
                "tmin_c": lo,
                "tmax_c": hi,
                **offset_errors(kind, args.seed, params, temps, **at),
            }
            end = r.get("end_temp_c")
            if isinstance(end, int | float):
                seen_hi = max(hi, float(end))
                seen = offset_errors(kind, args.seed, params, np.linspace(lo, seen_hi, 7), **at)
                res["seen"] = {"tmin_c": lo, "tmax_c": round(seen_hi, 2), **seen}
            results[kind] = res
            print(
                f"{kind} (board rotation {args.rotation}): first push after {res['pushed_after_s']} s; "
                f"pushes {r['pushes']}; range of the set held at the end {lo:.1f}..{hi:.1f} degC"
            )
            for i, t in enumerate(res["temps_c"]):
                print(f"  {t:6.1f} degC  before {res['before_dph'][i]}  after {res['after_dph'][i]} deg/h")
            print(f"  improvement (max over range, per axis): {res['improvement_x']}x")
            if "seen" in res:
                sn = res["seen"]
                worst_b = np.max(np.abs(sn["before_dph"]), axis=0).tolist()
                worst_a = np.max(np.abs(sn["after_dph"]), axis=0).tolist()
                print(f"  over the whole range seen {sn['tmin_c']:.1f}..{sn['tmax_c']:.1f} degC (clamped "
                      f"above TMAX): worst before {worst_b} after {worst_a} deg/h: {sn['improvement_x']}x")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
