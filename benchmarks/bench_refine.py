"""Benchmark: how many pushes a warm-up gives, and how wide the last set is (issue 10's refinement).

In process, on simulated time (tests/daemon_harness.py: the real Session, learner and store against
the virtual unit of our protocol): a still unit warming 20 -> 50 degC with time constant ``--tau``,
whose x axis barely drifts with temperature while y and z drift 0.1-0.2 deg/s over the warm-up (the
case of tests/test_daemon_refine.py), model ``1, temp, temp^2``. Prints each acked set's temperature
range and why it was pushed, then the thermal drift before/after the last set over its range [deg/h],
each less its mean (the switch-on bias is not the set's to judge here).

    python benchmarks/bench_refine.py --tau 600 --seconds 1800 --json out/bench_refine.json
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gyrocal.sim.truth import Thermal  # noqa: E402
from tests.test_daemon_refine import _acked, _shape_error, _warming_harness  # noqa: E402

DPH = 3600.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tau", type=float, default=60.0, help="warm-up time constant [s]")
    ap.add_argument("--seconds", type=float, default=240.0, help="simulated run length [s]")
    ap.add_argument("--json", metavar="OUT.json")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)
    with tempfile.TemporaryDirectory(prefix="bench_refine_") as tmp:
        h = _warming_harness(Path(tmp))
        h.unit.truth.thermal = Thermal(ambient_c=20.0, rise_c=30.0, tau_s=args.tau)
        h.switch_on()
        h.run(args.seconds)
        sets: list[dict[str, Any]] = []
        for v in _acked(h.store):
            rec = h.store.get(4242, v)
            assert rec is not None
            sets.append({"version": v, "temp_range_c": [round(x, 2) for x in rec.stats["temp_range_c"]],
                         "refinement": rec.stats["validation"].get("refinement")})
            print(f"v{v}: {sets[-1]['temp_range_c'][0]:.1f}..{sets[-1]['temp_range_c'][1]:.1f} degC  "
                  f"{sets[-1]['refinement'] or 'first set'}")
    out: dict[str, Any] = {"tau_s": args.tau, "seconds": args.seconds, "pushes": len(sets), "sets": sets}
    if sets:
        lo, hi = sets[-1]["temp_range_c"]
        before, after = _shape_error(h, h.store.get(4242, sets[-1]["version"]).coefficients_dps, lo, hi)
        out["before_dph"] = (before * DPH).round(1).tolist()
        out["after_dph"] = (after * DPH).round(1).tolist()
        print(f"{len(sets)} pushes; last set {lo:.1f}..{hi:.1f} degC; worst thermal drift before "
              f"{out['before_dph']} after {out['after_dph']} deg/h (x, y, z)")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
