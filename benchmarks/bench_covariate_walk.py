"""Is a covariate effect named as the covariate or as random_walk? (outside check H1, 2026-11-27)

    .venv/bin/python benchmarks/bench_covariate_walk.py [--seeds 100:112] [--json OUT.json]

Logs as ``gyrocal sim --rate 25 --duration 540 --power-cycle-every 180 --noise noise_dps=0.05`` makes
them, in-process: white gyro noise 0.05 deg/s per sample, 3 sessions x 180 s at 25 Hz, the 18-pose
tumble, the simulator's warm-up temperature course (+8 degC, tau 120 s after each switch-on). Two
sets, the effect on x only:

- ``temperature``: 0.003 deg/s per degC (T, dT/dt and exp(-t_on / 120 s) have one shape here, so a
  look-alike named with ``confounded_with`` listing temperature counts as right);
- ``pair``: 0.003 deg/s per degC + 0.15 deg/s per degC/s, with a 2 degC cycle over 240 s added to the
  course so the two separate.

Per log: the causes named (analysis in-process, the whole ``analyze``). Counted: random_walk named
(wrong: the noise is white), the true cause(s) named on x, any regression cause on y or z.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gyrocal.analysis.engine import analyze
from gyrocal.logformat import LogData
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import Effects, SessionStream, Thermal, TruthModel

SETS = {"temperature": (0.003, 0.0, 0.0), "pair": (0.003, 0.15, 2.0)}
"""set -> (temperature effect [deg/s per degC], rate effect [deg/s per degC/s], cycle [degC])."""


def white_log(seed: int, temp_dps_per_c: float, rate_dps_per_cps: float, cycle_c: float) -> dict:
    """Log columns: white gyro noise 0.05 deg/s, a temperature effect on x [deg/s per degC] and a
    temperature-rate effect on x [deg/s per degC/s]; the temperature warms 8 degC (tau 120 s) after
    each switch-on plus a cycle of ``cycle_c`` [degC] over 240 s (the module docstring)."""
    effects = Effects(temp_dps_per_c=np.array([temp_dps_per_c, 0.0, 0.0]),
                      temp_rate_dps_per_cps=np.array([rate_dps_per_cps, 0.0, 0.0]))
    model = TruthModel(noise_dps=0.05, thermal=Thermal(cycle_c=cycle_c, cycle_period_s=240.0),
                       effects=effects)
    parts = [SessionStream(model, tumble(), 25.0, seed, boot, t0_s=boot * 240.0).chunk(180 * 25)
             for boot in range(3)]
    keep = ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session")
    return {k: np.concatenate([p[k] for p in parts]) for k in keep}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="100:112", help="first:stop seeds per set (default 100:112)")
    ap.add_argument("--sets", default="temperature,pair")
    ap.add_argument("--json", help="write the rows and counts here")
    args = ap.parse_args(argv)
    lo, hi = (int(v) for v in args.seeds.split(":"))
    out: dict = {}
    for name in args.sets.split(","):
        temp, rate, cyc = SETS[name]
        truth = {"temperature"} if name == "temperature" else {"temperature", "temperature_rate"}
        rows = []
        for seed in range(lo, hi):
            found = analyze(LogData(white_log(seed, temp, rate, cyc), {}, [], name)).result["findings"]
            on = {f["cause"]: f for f in found}
            x = {c for c, f in on.items() if "x" in f["axes"] and c != "random_walk"}
            conf = {c for f in on.values() for c in (f["params"].get("confounded_with") or {}).get("x", [])}
            right = x == truth or (name == "temperature" and len(x) == 1 and "temperature" in x | conf)
            rows.append({"seed": seed, "named": {c: f["axes"] for c, f in on.items()}, "right": right,
                         "walk": "random_walk" in on,
                         "other_axes": sorted({a for c, f in on.items() for a in f["axes"]
                                               if a != "x" and c != "random_walk"})})
            print(json.dumps({"set": name, **rows[-1]}), flush=True)
        out[name] = {"logs": len(rows), "right": sum(r["right"] for r in rows),
                     "random_walk": sum(r["walk"] for r in rows),
                     "cause_on_y_or_z": sum(bool(r["other_axes"]) for r in rows), "rows": rows}
        print(f"{name}: {out[name]['right']}/{len(rows)} right, random_walk named on "
              f"{out[name]['random_walk']}, a cause on y or z on {out[name]['cause_on_y_or_z']}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
