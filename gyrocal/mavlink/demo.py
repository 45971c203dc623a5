"""`gyrocal demo --mavlink`: the daemon calibrates a virtual PX4 and a virtual ArduPilot, end to end.

For each autopilot it starts ``gyrocal sim --link mavlink --autopilot KIND`` on a pty (a board warming
from 20 to 50 degC, time constant ``tau_s``), runs the daemon's engine against it with the temperature
polynomial as its model, waits for the first acked push (parameters written with compensation off,
verified, enabled, read back), stops the autopilot and compares, from the autopilot's own truth, the
gyro offset error over the temperature range of the set it holds (TMIN..TMAX: the range seen, never
extrapolated), before and after, in deg/h (gyrocal/sim/autopilot_truth.py; the same figure as
benchmarks/bench_mavlink.py). A PX4 whose TC_G_ENABLE was 0 at boot applies the set at its next
reboot: the demo says so, as status does.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from gyrocal.daemon.config import load_config
from gyrocal.daemon.engine import Engine
from gyrocal.daemon.virtual import _read_line
from gyrocal.errors import LinkError

TERMS = ["1", "temp", "temp^2"]
"""The model: a quadratic in temperature (over one warm-up the daemon's rank test does not determine
the cubic; docs/mavlink.md). The autopilot holds it with a zero cubic."""


def _acked(engine: Engine) -> bool:
    s = engine.session
    return s is not None and (s.last_push or {}).get("status") == "acked"


def run_one(kind: str, seed: int, timeout_s: float, tau_s: float = 25.0,
            rate_hz: float = 250.0) -> dict[str, Any]:
    """Calibrate one virtual autopilot; return the push, the range and the before/after errors."""
    from gyrocal.sim.autopilot_truth import held_range, offset_errors

    with tempfile.TemporaryDirectory(prefix="gyrocal-demo-mavlink-") as tmp:
        work = Path(tmp)
        sim = subprocess.Popen(
            [sys.executable, "-m", "gyrocal.cli", "sim", "--link", "mavlink", "--autopilot", kind,
             "--rate", f"{rate_hz:g}", "--seed", str(seed), "--warmup-tau", f"{tau_s:g}",
             "--flash", str(work / "flash.json")],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )
        engine = None
        started = time.monotonic()
        try:
            url = _read_line(sim, 15.0).strip()
            if not url.startswith("/"):
                raise LinkError(f"the virtual autopilot did not print its pty path (got {url!r})")
            cfg = load_config(None, {
                "state_dir": str(work / "state"), "control_socket": str(work / "control.sock"),
                "link.kind": "mavlink", "link.url": url, "link.mavlink": {"autopilot": kind},
                "estimator.terms": TERMS, "watchdog": False,
            })
            engine = Engine(cfg)
            engine.open()
            hello_at: list[float] = []

            def until(e: Engine) -> bool:
                if not hello_at and e.session is not None:
                    hello_at.append(time.monotonic())
                return _acked(e)

            engine.run(until=until, timeout_s=timeout_s)
            session = engine.session
            push = dict(session.last_push) if session is not None else {}
            reboot = session.reboot_needed if session is not None else None
            status = dict(engine.status)
            first_push_s = round(time.monotonic() - hello_at[0], 1) if hello_at and push else None
        finally:
            if engine is not None:
                engine.close()
            sim.send_signal(signal.SIGTERM)
            try:
                sim.wait(15)
            except subprocess.TimeoutExpired:
                sim.kill()
                sim.wait()
        flash = json.loads((work / "flash.json").read_text()) if (work / "flash.json").exists() else {}
    res: dict[str, Any] = {
        "autopilot": kind, "seed": seed, "acked": push.get("status") == "acked",
        "version": push.get("version"),
        "reboot_needed": reboot, "elapsed_s": round(time.monotonic() - started, 1),
        "first_push_s": first_push_s, "state": status.get("state"), "reason": status.get("reason"),
        "unit_serial": (status.get("unit") or {}).get("serial"),
    }
    if res["acked"] and flash.get("params"):
        lo, hi = held_range(kind, flash["params"])
        res.update({"tmin_c": lo, "tmax_c": hi,
                    **offset_errors(kind, seed, flash["params"], np.linspace(lo, hi, 5))})
    return res


def improved(res: dict[str, Any]) -> bool:
    """Acked, and the worst offset error over the range is lower after than before, on every axis."""
    return bool(res.get("acked") and res.get("improvement_x")) and all(x > 1.0 for x in res["improvement_x"])


def print_table(res: dict[str, Any]) -> None:
    kind = {"px4": "PX4", "ardupilot": "ArduPilot"}[res["autopilot"]]
    if not res["acked"]:
        print(f"{kind}: no push acked after {res['elapsed_s']} s ({res['state']}: {res['reason']})")
        return
    print(f"{kind}: virtual autopilot {res['unit_serial']} (seed {res['seed']}) over a pty; "
          f"set v{res['version']} pushed and read back {res['first_push_s']} s after its HELLO; it holds "
          f"{res['tmin_c']:.1f}..{res['tmax_c']:.1f} degC (the range seen)")
    print(f"  {'temp':>11}   {'before x':>9} {'y':>9} {'z':>9}        {'after x':>9} {'y':>9} {'z':>9}"
          "   (offset error [deg/h]; temp [degC])")
    for t, b, a in zip(res["temps_c"], res["before_dph"], res["after_dph"], strict=True):
        cells = " ".join(f"{v:9.1f}" for v in b) + "        " + " ".join(f"{v:9.1f}" for v in a)
        print(f"  {t:11.1f}   {cells}")
    x = res["improvement_x"]
    print(f"  worst error over the range cut {x[0]:.0f}x / {x[1]:.0f}x / {x[2]:.0f}x (x / y / z)")
    if res.get("px4_staircase_dph"):
        step = max(res["px4_staircase_dph"])
        print(f"  (PX4 applies the offset in 1 degC steps: up to {step:.0f} deg/h more)")
    if res.get("reboot_needed"):
        print(f"  REBOOT NEEDED: {res['reboot_needed']['why']}; the figures are those of the set it holds")


def main(seed: int, timeout_s: float, as_json: bool, kinds: tuple[str, ...] = ("px4", "ardupilot"),
         tau_s: float = 25.0) -> int:
    results = [run_one(k, seed, timeout_s, tau_s) for k in kinds]
    if as_json:
        print(json.dumps({r["autopilot"]: r for r in results}, indent=1))
    else:
        for r in results:
            print_table(r)
    bad = [r["autopilot"] for r in results if not improved(r)]
    if bad:
        print(f"gyrocal demo --mavlink: no improvement pushed to {', '.join(bad)}", file=sys.stderr)
        return 1
    return 0
