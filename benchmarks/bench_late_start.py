"""A daemon that does not hear the unit from its first sample: what it learns, per case.

    .venv/bin/python benchmarks/bench_late_start.py [--cases warmup,dtemp,gap,lossy,own,pty,ptylossy,can]
        [--seeds 3] [--runs 4] [--json]

In simulated time through the daemon's own Session (tests/grade_harness.py), deterministic per seed.
On a vehicle the IMU streams from power-on while the navigation computer boots, systemd restarts a
daemon mid-session, and a link drops and comes back within a switch-on. The unit evaluates its set
on its own time since switch-on and its own dT/dt rule (docs/protocol.md, sections 4 and 6); the
daemon must rebuild both from what it heard.

- ``warmup``: the demo unit (sim/truth.py) plus a warm-up of 0.03 / -0.02 / 0.025 deg/s,
  exp(-t_on/300 s); the daemon's terms are seed 000's and exp(-t_on/300); it starts 150 s after the
  unit. Figure: the pushed warm-up coefficient over the true one, per axis (1 is right).
- ``dtemp``: the independent fibre unit's physics (tests/indep/inprocess.py, 400 Hz) holding a factory
  set on terms 0x549E with 0.02 / -0.015 / 0.01 deg/s per degC/s of dT/dt, in its warm-up; the
  daemon starts 0, 0.25, 0.5, 0.75 or 2.3 s late. Figure: the true drift cut of the first push
  over the unit's poses, per axis.
- ``gap``: the same unit and daemon from switch-on, with the link down for 3 s from 8 s, 0.3 s from
  8 s, or 1 s from 15 s. Figure: the cut, per axis.
- ``lossy``: the same unit and daemon from switch-on, on a link that loses a burst now and then
  (``LOSSY``). Figure: the cut, or no push within 150 s.
- ``own``: the demo unit with a dT/dt drift of 0.02 / -0.015 / 0.01 deg/s per degC/s and the
  daemon's own terms seed 000 + dtemp, 200 Hz, 300 s, on a clean link or one that loses 50 ms or
  0.5 s in every 5 s. Once the daemon's first set is held, the unit compensates with the daemon's own
  dtemp term. Figures: the pushes, the samples set aside, the samples learnt, the drift left.
- ``pty`` and ``can`` (not in the default cases: real time, about a minute a run): the case of
  tests/test_indep_unit.py::test_held_temperature_rate_set_is_reconstructed, run ``--runs`` times:
  the independent unit as a process on a pty with that factory set, the real daemon opening the port
  as soon as it is up, which is a part of a second into the unit's first second. Figure: the cut of
  the acked set per axis, from the unit's own truth. ``can``: the same on CAN (python-can
  ``udp_multicast``, node 3), where the daemon also starts after the unit. ``ptylossy``: the pty case through
  tests/lossy_pty.py, a pty that loses 0.2 s of the unit's bytes every 5 s (``LOSSY_LIVE``).

Each row also gives the samples the unit had sent at the push and ``dtemp_inexact_samples``.
To compare with an older commit, copy this file into a worktree of it and run it there.
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

from gyrocal.model.terms import SEED000_TERMS  # noqa: E402
from gyrocal.protocol import termsets  # noqa: E402
from gyrocal.sim.truth import Effects, TruthModel  # noqa: E402
from tests.grade_harness import GradeRun  # noqa: E402
from tests.indep.inprocess import (  # noqa: E402
    FACTORY_VERSION,
    IndepPhysicsUnit,
    factory_dtemp_set,
    held_dtemp_run,
    replaced_factory_set,
)

RATE_HZ = 400.0
WARMUP_DPS = np.array([0.03, -0.02, 0.025])
WARMUP_TAU_S = 300.0
LOSSY = ((0.0125, 2.0), (0.05, 5.0), (0.2, 10.0), (0.5, 15.0))
"""(burst lost [s], every [s]) of the ``lossy`` case: 5 frames at 400 Hz every 2 s up to half a
second every 15 s."""


def warmup(seed: int, late_s: float = 150.0) -> dict[str, Any]:
    terms = [*SEED000_TERMS, f"exp(-t_on/{WARMUP_TAU_S:g})"]
    termsets.register(terms)
    truth = TruthModel(effects=Effects(warmup_dps=WARMUP_DPS, warmup_tau_s=WARMUP_TAU_S))
    with tempfile.TemporaryDirectory() as d:
        run = GradeRun.make(Path(d), rate_hz=200.0, seed=seed, truth=truth, estimator={"terms": terms})
        run.switch_on()
        run.unit.render(int(late_s * 200.0))
        run.run(400.0, lambda r: bool(r.pushes) and r.unit.applied is not None
                and len(r.unit.applied.names) == len(terms))
        a = run.unit.applied
        row: dict[str, Any] = {"case": "warmup", "seed": seed, "late_s": late_s}
        if a is None or len(a.names) != len(terms):
            return row | {"pushed": False}
        ratio = a.coeffs_dps[:, -1] / WARMUP_DPS
        return row | {"pushed": True, "push_s": round(run.pushes[0]["t"], 2),
                      "learnt_over_true": dict(zip("xyz", ratio.round(3).tolist(), strict=True))}


def _cut_row(run: GradeRun, unit: IndepPhysicsUnit, row: dict[str, Any]) -> dict[str, Any]:
    assert run.session is not None
    row |= {"pushed": replaced_factory_set(run), "samples_at_push": unit.session_index,
            "dtemp_inexact_samples": run.session.status().get("dtemp_inexact_samples")}
    if row["pushed"]:
        before, after = unit.drift_rms_dps()
        row["cut"] = dict(zip("xyz", (before / after).round(1).tolist(), strict=True))
    return row


def dtemp(seed: int, late_s: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as d:
        run, unit = held_dtemp_run(Path(d), seed, RATE_HZ)
        run.switch_on()
        unit.render(int(late_s * RATE_HZ))  # sent before the daemon listened
        run.run(150.0, replaced_factory_set)
        return _cut_row(run, unit, {"case": "dtemp", "seed": seed, "late_s": late_s})


def gap(seed: int, at_s: float, down_s: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as d:
        run, unit = held_dtemp_run(Path(d), seed, RATE_HZ)
        run.switch_on()
        run.run(at_s)
        unit.render(int(down_s * RATE_HZ))  # lost on the link
        run.now += down_s
        run.run(150.0, replaced_factory_set)
        return _cut_row(run, unit, {"case": "gap", "seed": seed, "at_s": at_s, "down_s": down_s})


def _lose_bursts(run: GradeRun, burst_s: float, every_s: float, total_s: float, until: Any = None) -> None:
    """Run ``total_s`` of unit time from switch-on, ``burst_s`` of every ``every_s`` of it rendered by
    the unit but lost on the link; stop early once ``until(run)``."""
    t = 0.0
    while t < total_s and not (until is not None and until(run)):
        run.run(every_s - burst_s, until)
        if burst_s:
            run.unit.render(int(round(burst_s * run.rate_hz)))  # lost on the link
            run.now += burst_s
        t += every_s


def lossy(seed: int, burst_s: float, every_s: float, within_s: float = 150.0) -> dict[str, Any]:
    """The same unit and daemon from switch-on, on a link that loses ``burst_s`` of samples every
    ``every_s`` (a USB-serial adapter that overruns, a CAN bus that is busy): the first push within
    ``within_s`` of unit time, if any."""
    with tempfile.TemporaryDirectory() as d:
        run, unit = held_dtemp_run(Path(d), seed, RATE_HZ)
        run.switch_on()
        _lose_bursts(run, burst_s, every_s, within_s, replaced_factory_set)
        row = {"case": "lossy", "seed": seed, "burst_s": burst_s, "every_s": every_s}
        return _cut_row(run, unit, row)


OWN_TEMP_RATE_DPS_PER_CPS = np.array([0.02, -0.015, 0.01])


def own(seed: int, burst_s: float, every_s: float = 5.0, total_s: float = 300.0) -> dict[str, Any]:
    """The demo unit with a dT/dt drift, the daemon's own terms seed 000 + dtemp, 200 Hz, on a link
    that loses ``burst_s`` in every ``every_s`` from switch-on: after the daemon's first push the unit
    compensates with the daemon's own dtemp term, so every later sample needs the unit's dT/dt."""
    terms = [*SEED000_TERMS, "dtemp"]
    termsets.register(terms)  # the daemon's config does so now; 856f8f4's did not (its "before" row)
    truth = TruthModel(effects=Effects(temp_rate_dps_per_cps=OWN_TEMP_RATE_DPS_PER_CPS))
    with tempfile.TemporaryDirectory() as d:
        run = GradeRun.make(Path(d), rate_hz=200.0, seed=seed, truth=truth, estimator={"terms": terms})
        run.switch_on()
        _lose_bursts(run, burst_s, every_s, total_s)
        assert run.session is not None
        st = run.session.status()
        drift = run.unit.status()
        return {"case": "own", "seed": seed, "burst_s": burst_s, "every_s": every_s,
                "pushes": [[round(p["t"]), p["push"].get("status")] for p in run.pushes],
                "dtemp_inexact_samples": st.get("dtemp_inexact_samples"),
                "trained_samples": st.get("trained_samples"),
                "drift_raw_dps": {a: round(v, 6) for a, v in drift["drift_rms_raw_dps"].items()},
                "drift_left_dps": {a: round(v, 6) for a, v in drift["drift_rms_compensated_dps"].items()}}


LOSSY_LIVE = (0.2, 5.0)
"""(burst lost [s], every [s]) of wall time on the ``ptylossy`` line."""


def live(run: int, link: str = "pty") -> dict[str, Any]:
    from tests.indep.wire import CoeffSet
    from tests.sim_helpers import MULTICAST_GROUP, free_udp_port
    from tests.test_indep_unit import Daemon, IndepUnit, _acked, wait_for

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        flash = {"boot": 4, "set": CoeffSet(FACTORY_VERSION, 0x549E, factory_dtemp_set()).encode().hex()}
        (tmp / "flash.json").write_text(json.dumps(flash))
        proxy = None
        if link in ("pty", "ptylossy"):
            unit = IndepUnit(tmp, "--link", "pty", "--rate", "400", "--grade", "fibre")
            address = unit.address
            if link == "ptylossy":
                from tests.lossy_pty import LossyPty

                proxy = LossyPty(unit.address, *LOSSY_LIVE)
                address = proxy.address
            daemon = Daemon(tmp, {"kind": "serial", "url": address, "baudrate": 921600})
        else:
            port = free_udp_port()
            unit = IndepUnit(tmp, "--link", "can", "--node", "3", "--rate", "400", "--grade", "fibre",
                             "--can-channel", MULTICAST_GROUP, "--can-port", str(port))
            bus = {"interface": "udp_multicast", "channel": MULTICAST_GROUP, "port": port}
            daemon = Daemon(tmp, {"kind": "can", "can_node_id": 3, "can": bus})
        try:
            ok = wait_for(lambda: _acked(unit, daemon, 5), timeout_s=120.0, poll_s=0.5)
            truth, status = unit.truth(), daemon.status()
        finally:
            daemon.stop()
            unit.stop()
            if proxy is not None:
                proxy.close()
    session = status.get("session", status)
    row: dict[str, Any] = {"case": link, "run": run, "pushed": bool(ok),
                           "dtemp_inexact_samples": session.get("dtemp_inexact_samples")}
    if proxy is not None:
        row["dropped_bytes"] = proxy.dropped_bytes
        link_stats = status.get("link", {})
        errors = link_stats.get("errors", {})
        row["link"] = {"frames": link_stats.get("frames")} | {k: v for k, v in errors.items() if v}
    if ok:
        ack = [a for a in truth["acks"] if a["boot"] == 5][-1]
        row["samples_at_push"] = ack["seq_first"]
        row["cut"] = {a: round(ack["rms_before"][a] / ack["rms_after"][a], 1) for a in "xyz"}
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="warmup,dtemp,gap,lossy,own")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--runs", type=int, default=4, help="runs of the pty, ptylossy and can cases")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of lines")
    args = p.parse_args(argv)
    import logging

    logging.disable(logging.WARNING)  # the session's refusals; the rows say what happened
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    seeds = range(1, args.seeds + 1)
    cases = args.cases.split(",")
    for seed in seeds:
        if "warmup" in cases:
            rows.append(warmup(seed))
        if "dtemp" in cases:
            rows += [dtemp(seed, late) for late in (0.0, 0.25, 0.5, 0.75, 2.3)]
        if "gap" in cases:
            rows += [gap(seed, at, down) for at, down in ((8.0, 3.0), (8.0, 0.3), (15.0, 1.0))]
        if "lossy" in cases:
            rows += [lossy(seed, burst, every) for burst, every in LOSSY]
        if "own" in cases:
            rows += [own(seed, burst) for burst in (0.0, 0.05, 0.5)]
        if not args.json:
            shown = ("warmup" in cases) + 5 * ("dtemp" in cases) + 3 * ("gap" in cases) \
                + len(LOSSY) * ("lossy" in cases) + 3 * ("own" in cases)
            for r in rows[-shown:]:
                print(json.dumps(r), flush=True)
    for link in ("pty", "ptylossy", "can"):
        for run in range(args.runs if link in cases else 0):
            rows.append(live(run, link))
            if not args.json:
                print(json.dumps(rows[-1]), flush=True)
    if args.json:
        print(json.dumps({"rows": rows, "wall_s": round(time.perf_counter() - t0, 1)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
