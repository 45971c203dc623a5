"""The Earth's rotation in a unit at rest: what the daemon pushes with and without ``site.latitude_deg``.

    .venv/bin/python benchmarks/bench_earth.py [--grades fibre,tactical,demo] [--seeds 3]
        [--latitudes 45] [--headings 0,120] [--seconds 120] [--json]

In simulated time through the daemon's own Session (tests/grade_harness.py), deterministic per seed.
The virtual unit's truth has the Earth turning (``TruthModel.latitude_deg``, ``heading_deg``): its
gyros read 15.041 deg/h projected on their axes as true rate, which a real unit does and the virtual
unit did not before. The drift figures are the unit's own (sim/unit.py ``status``): the systematic
drift left in its output over the tumble's poses, true rate excluded. A set that has learnt the
Earth's rotation as drift shows it there.

Per grade, seed, latitude and heading, three runs: the truth without the Earth's rotation ("none",
the simulation as it was), with it and the daemon as before ("earth"), with it and the daemon told
the latitude ("earth+lat"). Figures: the time of the first push after the HELLO, and the drift RMS
per axis [deg/h] before and after it (the best set held by ``--seconds``). ``--lose 0.2,5``: the link
loses 0.2 s of samples in every 5 s (a gap during a move loses the daemon's reference frame;
``references`` counts the frames it started).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gyrocal.sim.grades import grade_truth  # noqa: E402
from tests.grade_harness import GradeRun  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_late_start import _lose_bursts  # noqa: E402 (the one burst loop)

DPH = 3600.0


def run(grade: str, seed: int, latitude: float | None, heading: float, told: bool, seconds: float,
        rate_hz: float, lose: tuple[float, float] | None = None) -> dict[str, Any]:
    truth = dataclasses.replace(grade_truth(grade, rate_hz), latitude_deg=latitude, heading_deg=heading)
    over = {"site.latitude_deg": latitude} if told else {}
    with tempfile.TemporaryDirectory() as tmp:
        r = GradeRun.make(Path(tmp), grade, rate_hz, seed, truth=truth, **over)
        r.switch_on()
        before = r.unit.status()["drift_rms_compensated_dps"]
        if lose is None:
            r.run(seconds)
        else:  # burst_s lost on the link in every every_s, from switch-on
            _lose_bursts(r, lose[0], lose[1], seconds)
        earth = r.session.status()["earth"]
        acked = [p for p in r.pushes if p["push"].get("status") == "acked"]
        after = r.unit.status()["drift_rms_compensated_dps"]
    xyz = "xyz"
    return {"grade": grade, "seed": seed, "latitude_deg": latitude, "heading_deg": heading,
            "case": "none" if latitude is None else ("earth+lat" if told else "earth"),
            "lose": lose, "references": None if earth is None else earth["references"],
            "pushes": len(acked), "first_push_s": round(acked[0]["t"], 1) if acked else None,
            "drift_before_dph": [round(before[a] * DPH, 3) for a in xyz],
            "drift_after_dph": [round(after[a] * DPH, 3) for a in xyz] if acked else None}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--grades", default="fibre,tactical,demo")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--latitudes", default="45")
    p.add_argument("--headings", default="0,120")
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--rate", type=float, default=400.0, help="sample rate [Hz]")
    p.add_argument("--lose", metavar="BURST_S,EVERY_S", default=None,
                   help="a link that loses BURST_S of samples in every EVERY_S (e.g. 0.2,5)")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of lines")
    args = p.parse_args(argv)
    import logging

    logging.disable(logging.WARNING)
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    for grade in args.grades.split(","):
        for seed in range(1, args.seeds + 1):
            cases = [(None, 0.0, False)]
            for lat in (float(x) for x in args.latitudes.split(",")):
                for hd in (float(x) for x in args.headings.split(",")):
                    cases += [(lat, hd, False), (lat, hd, True)]
            for lat, hd, told in cases:
                lose = None if args.lose is None else tuple(float(x) for x in args.lose.split(","))
                rows.append(run(grade, seed, lat, hd, told, args.seconds, args.rate, lose))
                if not args.json:
                    print(json.dumps(rows[-1]), flush=True)
    summary: dict[str, Any] = {}
    for r in rows:
        if r["drift_after_dph"] is None:
            continue
        key = f"{r['grade']} {r['case']}"
        summary.setdefault(key, []).append(r["drift_after_dph"])
    summary = {k: {"runs": len(v),
                   "drift_after_dph_median_axis_mean": round(float(np.median([np.mean(x) for x in v])), 3),
                   "worst_axis_dph": round(float(np.max(v)), 3)} for k, v in summary.items()}
    out = {"rows": rows, "summary": summary, "elapsed_s": round(time.perf_counter() - t0, 1)}
    print(json.dumps(out if args.json else {"summary": summary, "elapsed_s": out["elapsed_s"]}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
