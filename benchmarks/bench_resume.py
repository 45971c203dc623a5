"""Daemon restarts within one switch-on: the versions they mint and the drift they leave.

    .venv/bin/python benchmarks/bench_resume.py [--seeds 6] [--restarts 4] [--every 30] [--no-resume]
        [--json]

In simulated time through the daemon's own Session (tests/daemon_harness.py: the demo unit, 400 Hz,
deterministic per seed). Per seed, two cases:

- ``full``: the unit's first switch-on, calibrated until its first (full) set is acked;
- ``bias``: then a power cycle, calibrated until its bias-only set is acked.

Then the daemon is restarted ``--restarts`` times, ``--every`` seconds apart, within that same
switch-on, the way the engine starts a session at a HELLO (same boot counter, the unit's clock going
on). Figures: the versions held after each restart with their stage, and the drift left on the unit's
poses [deg/h] at the end. ``--no-resume`` runs the sessions as before the resume existed (every
restart a new switch-on to the session), for the comparison.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gyrocal.daemon.learner import make_learner  # noqa: E402
from gyrocal.daemon.session import Session, same_boot  # noqa: E402
from gyrocal.daemon.stillness import StillDetector  # noqa: E402
from tests.daemon_harness import RATE_HZ, Harness  # noqa: E402

# Every run's store lives under one directory, removed when the script ends (each run left its own in /tmp)
_SCRATCH = tempfile.TemporaryDirectory(prefix="bench-resume-")


def _scratch() -> Path:
    """A fresh directory for one run's store, under the script's scratch directory."""
    return Path(tempfile.mkdtemp(dir=_SCRATCH.name))


def _acked(h: Harness) -> bool:
    return h.session is not None and h.session.last_push.get("status") == "acked"


def run_case(seed: int, case: str, restarts: int, every_s: float, resume: bool) -> dict[str, Any]:
    """One unit, calibrated into ``case``, then restarted within its switch-on; see module doc."""
    h = Harness.make(_scratch(), seed=seed)
    h.switch_on()
    h.run(90, until=_acked)
    if case == "bias":
        h.switch_on()
        h.run(60, until=_acked)
    held = h.store.held_last(4242)
    versions = []
    for _ in range(restarts):
        prior = h.store.held_last(4242)
        hello = h.session.hello
        h.detector = StillDetector.for_rate(RATE_HZ, h.cfg.still)
        h.session = Session(h.cfg, hello, make_learner(h.cfg, prior, RATE_HZ), h.store, h.send, h.now,
                            RATE_HZ, prior.version, same_boot=same_boot(prior, hello) if resume else None)
        h.run(every_s)
        rec = h.store.held_last(4242)
        versions.append([rec.version, (rec.stats.get("validation") or {}).get("stage")])
    drift = h.unit.status()["drift_rms_compensated_dps"]
    return {"seed": seed, "case": case, "resume": resume, "held_before": held.version,
            "held_after_each_restart": versions,
            "minted": versions[-1][0] - held.version,
            "drift_left_dph": {a: round(v * 3600.0, 3) for a, v in drift.items()}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--restarts", type=int, default=4)
    ap.add_argument("--every", type=float, default=30.0, help="[s] of unit time between restarts")
    ap.add_argument("--no-resume", action="store_true", help="every restart taken as a new switch-on")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = []
    for seed in range(1, args.seeds + 1):
        for case in ("full", "bias"):
            rows.append(run_case(seed, case, args.restarts, args.every, not args.no_resume))
            if not args.json:
                print(json.dumps(rows[-1]), flush=True)
    if args.json:
        print(json.dumps({"rows": rows, "wall_s": round(time.perf_counter() - t0, 1)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
