"""Issue 9's acceptance on a unit that is not gyrocal's own: the independent unit of tests/indep/.

    .venv/bin/python benchmarks/bench_indep.py [--quick] [--json] [--rates 400,1000,2000]
        [--grades fibre,mems] [--links pty,can] [--seeds 3] [--parallel 2] [--cycle]

The unit (``python -m tests.indep.unit``) was written from docs/protocol.md alone: its own framing,
CAN packing, drift truth (per-unit gravity terms, a new bias at every switch-on), random poses held
0.8-3 s, warm-up temperature and white noise (fibre 0.002 deg/s, mems 0.1 deg/s per sample). The
real daemon (``python -m gyrocal.cli run``) runs against it as a separate process, in real time.
Per run it reports, from the unit's own truth and the daemon's status:

- ``t_first_push_s``: wall time from start to the unit's first ACK;
- ``before`` / ``after``: the unit's true drift RMS over its 24 poses [deg/h] without compensation
  and with the acked set, and ``cut`` = before / after per axis (the issue asks >= 10x);
- ``false_alarms``: drift alarms in the daemon's log (the unit's drift law does not change within a
  switch-on, so every one is false);
- ``predicted``: what the daemon expected the set to leave (``expected``: the geometric mean of
  the figures over the poses seen and over the sphere, since the unit's poses are some of each), and
  ``pred_ratio`` = measured / predicted (the issue asks within 2x); ``predicted_bound`` and
  ``pred_ratio_bound`` the same for the gate's figure (``left``: the worse of the two, an upper bound),
  ``predicted_poses_seen`` and ``pred_ratio_poses_seen`` for the poses seen only;
- with ``--cycle``: a power cycle after the first push, and ``t_cycle_push_s``, the time from the new
  HELLO to the ACK of the new bias (the unit holds its first pose from switch-on, so its first still
  second ends about 1 s after the HELLO; the issue asks for the bias within 10 s of it), the cut
  of that push, and ``vs_held``: the drift it leaves over what the held set left at its own push (a
  bias-only push keeps the held set's gravity terms, so it is judged as: 10x, or within 3x of that).

Runs take 30-60 s each; ``--parallel`` runs that many at once (2 on a 2-core machine).

``--inprocess`` runs the same truth, schedule and noise against the daemon's Session in process
(tests/indep/inprocess.py: no wire, no processes, the samples' own clock), about 1 s a run, for the
statistics of the first push and its prediction over many seeds (``--seeds 40``); ``--links`` and
``--cycle`` do not apply.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from tests.sim_helpers import MULTICAST_GROUP, free_udp_port, wait_for  # noqa: E402
from tests.test_indep_unit import Daemon, IndepUnit, _acked  # noqa: E402

DPH = 3600.0
AXES = "xyz"


def _ack(unit: IndepUnit, boot: int) -> dict[str, Any] | None:
    acks = [a for a in unit.truth().get("acks", []) if a["boot"] == boot]
    return acks[-1] if acks else None


def _figures(ack: dict[str, Any], pred: dict[str, Any] | None) -> dict[str, Any]:
    before = {a: ack["rms_before"][a] * DPH for a in AXES}
    after = {a: ack["rms_after"][a] * DPH for a in AXES}
    pred = pred or {}
    bound = pred.get("bound") or pred.get("left") or {}
    seen = pred.get("left_poses") or {}
    expected = pred.get("expected") or {}

    def ratio(p: dict[str, Any]) -> dict[str, float | None]:
        return {a: (after[a] / p[a] if p.get(a) else None) for a in AXES}

    return {"before": before, "after": after,
            "cut": {a: before[a] / max(after[a], 1e-12) for a in AXES},
            "predicted": expected, "predicted_bound": bound, "predicted_poses_seen": seen,
            "stage": pred.get("stage"), "pred_ratio": ratio(expected), "pred_ratio_bound": ratio(bound),
            "pred_ratio_poses_seen": ratio(seen)}


def run_one(link: str, grade: str, rate: int, seed: int, cycle: bool, timeout_s: float) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="bench_indep_"))
    args = ["--rate", str(rate), "--grade", grade, "--seed", str(seed), "--serial", str(0x5EED0000 + seed)]
    if link == "can":
        port = free_udp_port()
        unit = IndepUnit(tmp, "--link", "can", "--node", "3", "--can-channel", MULTICAST_GROUP,
                         "--can-port", str(port), *args)
        cfg = {"kind": "can", "can_node_id": 3,
               "can": {"interface": "udp_multicast", "channel": MULTICAST_GROUP, "port": port}}
    else:
        unit = IndepUnit(tmp, "--link", "pty", *args)
        cfg = {"kind": "serial", "url": unit.address, "baudrate": 921600}
    t0 = time.monotonic()
    daemon = Daemon(tmp, cfg)
    row: dict[str, Any] = {"link": link, "grade": grade, "rate_hz": rate, "seed": seed}
    try:
        if not wait_for(lambda: _acked(unit, daemon, 1), timeout_s=timeout_s, poll_s=0.5):
            row["error"] = f"no acked push in {timeout_s:g} s: {daemon.status().get('reason')}"
            return row
        row["t_first_push_s"] = round(time.monotonic() - t0, 1)
        st = daemon.status()
        row.update(_figures(_ack(unit, 1), st.get("last_push", {}).get("predicted_drift_dph")))
        if cycle:
            unit.power_cycle()
            if not wait_for(lambda: unit.truth().get("boot") == 2, timeout_s=20, poll_s=0.1):
                row["error"] = "the unit did not power-cycle"
                return row
            t1 = time.monotonic()
            if not wait_for(lambda: _acked(unit, daemon, 2), timeout_s=timeout_s, poll_s=0.2):
                row["error"] = f"no push after the power cycle: {daemon.status().get('reason')}"
                return row
            row["t_cycle_push_s"] = round(time.monotonic() - t1, 1)
            st = daemon.status()
            cyc = _figures(_ack(unit, 2), st.get("last_push", {}).get("predicted_drift_dph"))
            # a bias-only push keeps the held set's gravity terms: judged against what that set left
            row["cycle"] = {"cut": cyc["cut"], "after": cyc["after"], "stage": cyc["stage"],
                            "vs_held": {a: cyc["after"][a] / max(row["after"][a], 1e-12) for a in AXES}}
            row["sessions"] = st.get("sessions")
        # the unit's drift law does not change within a switch-on: every drift alarm is false
        row["false_alarms"] = daemon.log().count("drift alarm")
        return row
    finally:
        daemon.stop()
        unit.stop()


def run_inprocess(grade: str, rate: int, seed: int, timeout_s: float) -> dict[str, Any]:
    from tests.indep.inprocess import first_push
    with tempfile.TemporaryDirectory(prefix="bench_indep_") as tmp:
        r = first_push(Path(tmp), grade, float(rate), seed, max_s=timeout_s)
    row: dict[str, Any] = {"link": "inproc", "grade": grade, "rate_hz": rate, "seed": seed}
    if not r["pushed"]:
        row["error"] = f"no push in {timeout_s:g} s"
        return row
    row["t_first_push_s"] = r["t_first_push_s"]
    row.update(_figures({"rms_before": {a: v / DPH for a, v in r["before"].items()},
                         "rms_after": {a: v / DPH for a, v in r["after"].items()}}, r["predicted_drift_dph"]))
    oracle = r["at_unit_poses_dph"]
    row["pred_ratio_at_unit_poses"] = {a: (row["after"][a] / oracle[a] if oracle.get(a) else None)
                                       for a in AXES}
    row["false_alarms"] = 0  # not watched in process (the live runs count them)
    return row


def _fmt(row: dict[str, Any]) -> str:
    head = f"{row['link']:3} {row['grade']:5} {row['rate_hz']:5d} Hz seed {row['seed']}"
    if "error" in row and "cut" not in row:
        return f"{head}: ERROR {row['error']}"
    cut = "/".join(f"{row['cut'][a]:.0f}" for a in AXES)
    ratio = "/".join(f"{row['pred_ratio'][a]:.2f}" if row["pred_ratio"][a] else "-" for a in AXES)
    out = f"{head}: first push {row['t_first_push_s']:5.1f} s, cut {cut}x, measured/predicted {ratio}"
    if "cycle" in row:
        ccut = "/".join(f"{row['cycle']['cut'][a]:.0f}" for a in AXES)
        held = "/".join(f"{row['cycle']['vs_held'][a]:.2f}" for a in AXES)
        out += (f"; after power cycle {row['cycle']['stage']} push {row['t_cycle_push_s']:.1f} s, "
                f"cut {ccut}x, drift left / held set's {held}")
    if "error" in row:
        out += f"; ERROR {row['error']}"
    return out


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in rows if "cut" in r]
    cuts = [r["cut"][a] for r in ok for a in AXES]
    ratios = [r["pred_ratio"][a] for r in ok for a in AXES if r["pred_ratio"][a]]
    cyc = [r for r in ok if "cycle" in r]
    return {
        "runs": len(rows), "errors": len(rows) - len(ok) + sum(1 for r in ok if "error" in r),
        "axes": len(cuts), "axes_cut_ge_10": sum(c >= 10 for c in cuts),
        "worst_cut": round(min(cuts), 1) if cuts else None,
        "pred_within_2x": sum(0.5 <= q <= 2.0 for q in ratios), "pred_axes": len(ratios),
        # in process only: the same learner at the unit's own poses (what no daemon can know)
        "at_unit_poses_within_2x": sum(0.5 <= ((r.get("pred_ratio_at_unit_poses") or {}).get(a) or 0.0) <= 2.0
                                       for r in ok for a in AXES),
        # the measured drift against the gate's upper bound, and against [poses seen / 2, bound * 2]
        "under_bound": sum((r["pred_ratio_bound"][a] or 0.0) <= 1.0 for r in ok for a in AXES),
        "pred_in_range_2x": sum((r["pred_ratio_bound"][a] or 9.0) <= 2.0
                                and (r["pred_ratio_poses_seen"][a] or 0.0) >= 0.5 for r in ok for a in AXES),
        "t_first_push_s_max": max((r["t_first_push_s"] for r in ok), default=None),
        "cycle_runs": len(cyc),
        "cycle_t_push_s_max": max((r["t_cycle_push_s"] for r in cyc), default=None),
        "cycle_worst_cut": (round(min(r["cycle"]["cut"][a] for r in cyc for a in AXES), 1) if cyc else None),
        "cycle_axes_ok": sum(r["cycle"]["cut"][a] >= 10 or r["cycle"]["vs_held"][a] <= 3
                             for r in cyc for a in AXES),
        "cycle_worst_vs_held": (round(max(r["cycle"]["vs_held"][a] for r in cyc for a in AXES), 2)
                                if cyc else None),
        "false_alarms": sum(r.get("false_alarms", 0) for r in ok),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="one fibre run at 400 Hz on each link")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--rates", default="400,1000,2000")
    p.add_argument("--grades", default="fibre,mems")
    p.add_argument("--links", default="pty,can")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--parallel", type=int, default=2)
    p.add_argument("--cycle", action="store_true", help="power-cycle after the first push")
    p.add_argument("--timeout", type=float, default=120.0, help="per push [s]")
    p.add_argument("--inprocess", action="store_true",
                   help="the unit's physics against the daemon's Session in process (~1 s a run)")
    a = p.parse_args()
    if a.quick:
        a.rates, a.grades, a.seeds = "400", "fibre", 1
    rows: list[dict[str, Any]] = []
    if a.inprocess:
        cases = [(grade, int(rate), seed) for grade in a.grades.split(",") for rate in a.rates.split(",")
                 for seed in range(1, a.seeds + 1)]
        results = (run_inprocess(*c, a.timeout) for c in cases)
    else:
        cases = [(link, grade, int(rate), seed) for grade in a.grades.split(",")
                 for rate in a.rates.split(",") for link in a.links.split(",")
                 for seed in range(1, a.seeds + 1)]
        pool = ThreadPoolExecutor(max_workers=max(1, a.parallel))
        results = (f.result() for f in [pool.submit(run_one, *c, a.cycle, a.timeout) for c in cases])
    for row in results:
        rows.append(row)
        if not a.json:
            print(_fmt(row), flush=True)
    summ = summary(rows)
    if a.json:
        print(json.dumps({"rows": rows, "summary": summ}, indent=1))
    else:
        print(json.dumps(summ))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
