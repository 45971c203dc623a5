"""A switch-on whose bias moves on some axes and repeats on others: the drift left after each push.

Why: a unit whose y bias repeats from one switch-on to the next held x and z 1130 / 2874 deg/h off
for good (a serial integrator's consumer unit): the bias stage asked every axis to gain 3x, which
the repeating axis, already right, never could. This drives the daemon's session in process (the
grade harness of the tests) through a first calibration and a second switch-on whose bias moves by
``--move`` [deg/s] per axis, and prints the drift [deg/h] before and after each push of the second
switch-on, with the axes each push kept.

    python benchmarks/repeat_axis.py                       # consumer, 1 kHz, 0.1 deg/s, y repeats
    python benchmarks/repeat_axis.py --move 0.3,0,0 --json  # only x moves
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gyrocal.sim.grades import grade_truth  # noqa: E402
from tests.grade_harness import GradeRun, first_push  # noqa: E402

DPH = 3600.0


def run(grade: str, rate_hz: float, noise_dps: float, move: np.ndarray, seed: int, after_s: float) -> dict:
    truth = grade_truth(grade, rate_hz)
    truth.noise_dps = noise_dps
    real = truth.switch_on_bias
    truth.switch_on_bias = lambda s, boot: real(s, 1) + (0.0 if boot == 1 else move)  # type: ignore[method-assign]
    with tempfile.TemporaryDirectory() as tmp:
        r = GradeRun.make(Path(tmp), rate_hz=rate_hz, seed=seed, truth=truth)
        r.switch_on()
        r.run(180, until=first_push)
        r.run(2)
        r.pushes.clear()
        r.switch_on()
        before = r.unit.status()["drift_rms_compensated_dps"]
        r.run(after_s)
        pushes = [{"t_s": round(p["t"], 1),  # unit time since the second HELLO
                   "stage": p["push"]["predicted_drift_dph"].get("stage"),
                   "kept_axes": p["push"]["predicted_drift_dph"].get("kept_axes", []),
                   "drift_after_dph": {a: round(v * DPH, 2) for a, v in p["drift"].items()}}
                  for p in r.pushes]
        return {"grade": grade, "rate_hz": rate_hz, "noise_dps": noise_dps, "move_dps": move.tolist(),
                "seed": seed, "drift_before_dph": {a: round(v * DPH, 1) for a, v in before.items()},
                "pushes": pushes}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grade", default="consumer")
    p.add_argument("--rate", type=float, default=1000.0, help="sample rate [Hz]")
    p.add_argument("--noise", type=float, default=0.1, help="white noise per sample [deg/s]")
    p.add_argument("--move", default="0.3,0,-0.5", help="the second switch-on's bias change x,y,z [deg/s]")
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--after", type=float, default=120.0, help="unit time run after the switch-on [s]")
    p.add_argument("--json", action="store_true")
    a = p.parse_args()
    move = np.array([float(v) for v in a.move.split(",")])
    out = run(a.grade, a.rate, a.noise, move, a.seed, a.after)
    if a.json:
        print(json.dumps(out, indent=2))
        return 0
    b = out["drift_before_dph"]
    print(f"{a.grade}, {a.rate:g} Hz, {a.noise:g} deg/s, bias move {a.move} deg/s: before "
          f"{b['x']}/{b['y']}/{b['z']} deg/h")
    for q in out["pushes"]:
        d = q["drift_after_dph"]
        print(f"  push at {q['t_s']} s ({q['stage']}, kept {','.join(q['kept_axes']) or 'none'}): "
              f"{d['x']}/{d['y']}/{d['z']} deg/h")
    if not out["pushes"]:
        print("  no push")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
