"""A bias step within a switch-on, and none: what the daemon's step check finds and the drift it leaves.

    .venv/bin/python benchmarks/bench_bias_step.py [--seeds 2] [--at 3,10,20,30,40] [--step-dph 60]
        [--warm-at 1,1.5,2.5,3,4] [--step-dph-warm 100] [--null-seeds 3] [--json]

In simulated time through the daemon's own Session (tests/daemon_harness.py and tests/grade_harness.py,
deterministic per seed). Three parts:

- ``steps``: the demo unit's first switch-on (a cold tumble, 400 Hz); its x bias steps by
  ``--step-dph`` at each of ``--at`` seconds. Per run: the steps found (daemon/stepcheck.py), when the
  first set after the step was acked (``push_after_s``, seconds after the step; null if none in 150 s)
  and the unit's truth x drift left then [deg/h] (``x_left_dph``), beside the x bias it would keep
  uncalibrated (``x_raw_dph``).
- ``warm``: the demo unit calibrated on its tumble, switched on again at rest (z up); its x bias
  steps by ``--step-dph-warm`` at each of ``--warm-at`` seconds, with the held set's bias right
  (``held_right``: no push is due, the held set is watched) or moved since the last switch-on (its
  first bias stage is due). Per run: the steps found, the seconds of the next 60 s with the unit's
  x drift over 10 deg/h while status says `alarm: false` (``over_10_no_alarm_s``), and x left 60 s
  after the step [deg/h].
- ``nulls``: no step made. Each grade of sim/grades.py (``--null-seeds`` seeds, 200 Hz): a cold
  tumble of 400 s, then a warm switch-on of 200 s; and the demo unit's warm drives with turns too
  slow for the still rule (a roll of 0.06 deg in 1.1 s between rests; a settling of 5 steps of
  0.06 deg). Per run: the steps found, which should be none.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gyrocal.sim.grades import GRADES  # noqa: E402
from gyrocal.sim.schedule import Schedule, still  # noqa: E402
from tests.daemon_harness import Harness  # noqa: E402
from tests.grade_harness import GradeRun  # noqa: E402
from tests.test_still_rule import _tilted  # noqa: E402

DPH = 3600.0


# Every run's store lives under one directory, removed when the script ends (each run left its own in /tmp)
_SCRATCH = tempfile.TemporaryDirectory(prefix="bench-step-")


def _scratch() -> Path:
    """A fresh directory for one run's store, under the script's scratch directory."""
    return Path(tempfile.mkdtemp(dir=_SCRATCH.name))


def _acked(h: Harness) -> bool:
    return h.session is not None and h.session.last_push.get("status") == "acked"


def step_run(seed: int, at_s: float, step_dph: float) -> dict[str, Any]:
    """A cold tumble whose x bias steps by ``step_dph`` [deg/h] ``at_s`` [s] after switch-on."""
    t0 = time.process_time()
    h = Harness.make(_scratch(), seed=seed)
    h.switch_on()
    h.run(at_s)
    before = h.session.last_push.get("version")
    h.unit.stream.bias_dps = h.unit.stream.bias_dps + np.array([step_dph, 0.0, 0.0]) / DPH

    def acked_after() -> bool:
        p = h.session.last_push
        return p.get("status") == "acked" and p.get("version") != before

    waited = 0.0
    while waited < 150.0 and not acked_after():
        h.run(0.5)
        waited += 0.5
    unit = h.unit.status()
    return {"seed": seed, "at_s": at_s, "pushed_before_step": before is not None,
            "steps": h.session.bias_steps, "push_after_s": waited if acked_after() else None,
            "x_left_dph": round(unit["drift_rms_compensated_dps"]["x"] * DPH, 2),
            "x_raw_dph": round(unit["drift_rms_raw_dps"]["x"] * DPH, 2),
            "cpu_s": round(time.process_time() - t0, 1)}


def warm_step_run(seed: int, at_s: float, step_dph: float, held_right: bool) -> dict[str, Any]:
    """A warm switch-on at rest whose x bias steps by ``step_dph`` [deg/h] ``at_s`` [s] after it."""
    t0 = time.process_time()
    h = Harness.make(_scratch(), seed=seed)
    h.switch_on()
    h.run(90, until=_acked)
    h.run(2)
    bias = h.unit.stream.bias_dps.copy()
    h.unit.schedule = still((0.0, 0.0, 1.0))
    h.switch_on()
    if held_right:
        h.unit.stream.bias_dps = bias.copy()
    h.run(at_s)
    h.unit.stream.bias_dps = h.unit.stream.bias_dps + np.array([step_dph, 0.0, 0.0]) / DPH
    over = 0.0
    for _ in range(120):
        h.run(0.5)
        x = h.unit.status()["drift_rms_compensated_dps"]["x"] * DPH
        over += 0.5 if x > 10.0 and not h.session.alarm else 0.0
    return {"seed": seed, "at_s": at_s, "held_right": held_right, "steps": h.session.bias_steps,
            "over_10_no_alarm_s": over, "x_left_dph": round(x, 2),
            "cpu_s": round(time.process_time() - t0, 1)}


def grade_null(grade: str, seed: int) -> dict[str, Any]:
    """A cold tumble of 400 s and a warm switch-on of 200 s of one grade, no step made."""
    r = GradeRun.make(_scratch(), grade=grade, rate_hz=200.0, seed=seed)
    r.switch_on()
    r.run(400.0)
    cold = r.session.bias_steps
    r.switch_on()
    r.run(200.0)
    return {"case": f"{grade} cold+warm", "seed": seed, "steps": cold + r.session.bias_steps}


def drive_null(kind: str, seed: int) -> dict[str, Any]:
    """The demo unit calibrated on its tumble, then switched on for a 150 s drive of slow turns."""
    h = Harness.make(_scratch(), seed=seed)
    h.switch_on()
    h.run(90, until=_acked)
    h.run(3)
    if kind == "roll":
        poses = [_tilted(0, 0), _tilted(0.06, 0), _tilted(0.06, 0.06), _tilted(0, 0.06)]
        h.unit.schedule = Schedule(np.array(poses), 3.0, 1.1)
    else:
        h.unit.schedule = Schedule(np.array([_tilted(0.06 * min(i, 5), 0) for i in range(200)]), 1.0, 1.1)
    h.switch_on()
    h.run(150)
    left = h.unit.status()["drift_rms_compensated_dps"]
    return {"case": f"{kind} drive", "seed": seed, "steps": h.session.bias_steps,
            "left_dph": {a: round(v * DPH, 2) for a, v in left.items()}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=2, help="unit seeds of the step runs")
    ap.add_argument("--at", default="3,10,20,30,40", help="step times after switch-on [s]")
    ap.add_argument("--step-dph", type=float, default=60.0)
    ap.add_argument("--warm-at", default="1,1.5,2.5,3,4", help="step times after a warm switch-on [s]")
    ap.add_argument("--step-dph-warm", type=float, default=100.0)
    ap.add_argument("--null-seeds", type=int, default=3, help="seeds per grade and per drive (0: none)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    steps, warm, nulls = [], [], []
    for seed in range(1, args.seeds + 1):
        for at in (float(a) for a in args.at.split(",") if a):
            steps.append(step_run(seed, at, args.step_dph))
            if not args.json:
                print(json.dumps(steps[-1]), flush=True)
        for held_right in (True, False):
            for at in (float(a) for a in args.warm_at.split(",") if a):
                warm.append(warm_step_run(seed, at, args.step_dph_warm, held_right))
                if not args.json:
                    print(json.dumps(warm[-1]), flush=True)
    for seed in range(1, args.null_seeds + 1):
        for grade in GRADES:
            nulls.append(grade_null(grade, seed))
            if not args.json:
                print(json.dumps(nulls[-1]), flush=True)
        for kind in ("roll", "settle"):
            nulls.append(drive_null(kind, seed))
            if not args.json:
                print(json.dumps(nulls[-1]), flush=True)
    found = [r for r in steps if r["steps"]]
    pushed = [r for r in steps if r["push_after_s"] is not None]
    summary = {
        "step_runs": len(steps), "steps_found": len(found),
        "push_after_s": [min((r["push_after_s"] for r in pushed), default=None),
                         max((r["push_after_s"] for r in pushed), default=None)],
        "x_left_dph": [min((r["x_left_dph"] for r in pushed), default=None),
                       max((r["x_left_dph"] for r in pushed), default=None)],
        "warm_runs": len(warm), "warm_steps_found": sum(bool(r["steps"]) for r in warm),
        "warm_over_10_no_alarm_s": [min((r["over_10_no_alarm_s"] for r in warm), default=None),
                                    max((r["over_10_no_alarm_s"] for r in warm), default=None)],
        "warm_x_left_dph": [min((r["x_left_dph"] for r in warm), default=None),
                            max((r["x_left_dph"] for r in warm), default=None)],
        "null_runs": len(nulls), "null_runs_with_a_step": sum(bool(r["steps"]) for r in nulls)}
    out = {"step_dph": args.step_dph, "step_dph_warm": args.step_dph_warm, "steps": steps, "warm": warm,
           "nulls": nulls, "summary": summary}
    print(json.dumps(out, indent=1) if args.json else json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
