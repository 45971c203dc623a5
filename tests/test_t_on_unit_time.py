"""A late daemon learns a warm-up on the unit's time since switch-on, not on its own first sample.

Why: the unit evaluates exp(-t_on/TAU) with its own unit time since switch-on (docs/protocol.md,
sections 4 and 6). On a vehicle the IMU streams from power-on while the navigation computer is still
booting, and systemd restarts a daemon mid-session; the daemon's first sample is then D seconds
after the switch-on. A daemon that counted t_on from its own first sample saw exp(D/TAU) times the
unit's term, learnt the warm-up scaled by exp(-D/TAU) and pushed it: with TAU 300 s and D 150 s
it pushed 0.52-0.70 of the warm-up (benchmarks/bench_late_start.py at 24d9300, seeds 1-3), and every
later switch-on kept 30-48 % of its warm-up. Counted from the switch-on: 0.86-1.16.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from gyrocal.daemon.ring import SAMPLE_DTYPE
from gyrocal.model.terms import SEED000_TERMS
from gyrocal.protocol import termsets
from gyrocal.sim.truth import Effects, TruthModel
from tests.grade_harness import GradeRun

RATE_HZ = 200.0
TAU_S = 300.0
WARMUP_DPS = np.array([0.03, -0.02, 0.025])  # 108, -72, 90 deg/h at switch-on


def test_a_daemon_that_starts_150_s_after_the_unit_learns_the_whole_warm_up(tmp_path: Path) -> None:
    terms = [*SEED000_TERMS, f"exp(-t_on/{TAU_S:g})"]
    termsets.register(terms)  # the unit's firmware knows the set (else it NAKs the push)
    truth = TruthModel(effects=Effects(warmup_dps=WARMUP_DPS, warmup_tau_s=TAU_S))
    run = GradeRun.make(tmp_path, rate_hz=RATE_HZ, seed=1, truth=truth, estimator={"terms": terms})
    run.switch_on()
    run.unit.render(int(150 * RATE_HZ))  # streamed while the daemon was not yet listening
    run.run(300.0, lambda r: r.unit.applied is not None and len(r.unit.applied.names) == len(terms))
    applied = run.unit.applied
    assert applied is not None and len(applied.names) == len(terms), run.session.reason
    learnt = applied.coeffs_dps[:, -1]  # deg/s per unit of exp(-t_on/300)
    # counted from the daemon's first sample this is exp(-150/300) = 0.61 of the truth
    assert np.all(np.abs(learnt / WARMUP_DPS - 1) < 0.25), learnt / WARMUP_DPS


def test_a_unit_whose_clock_does_not_start_at_switch_on_gets_one_warning(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """t_on is the unit's time; a unit stamping its seq 0 at 5000 s breaks that, and is told so once."""
    run = GradeRun.make(tmp_path, rate_hz=RATE_HZ, seed=1)
    run.switch_on()
    caplog.set_level(logging.WARNING, logger="gyrocal.session")
    for first in (0, 100):  # two batches: the warning is for the session's first one only
        block = np.zeros(100, dtype=SAMPLE_DTYPE)
        block["seq"] = np.arange(first, first + 100)
        block["t"] = 5000.0 + block["seq"] / RATE_HZ
        block["az"] = 1.0
        run.session.feed(block, np.ones(100, dtype=bool), 1.0)
    said = [r.getMessage() for r in caplog.records if "counts from switch-on" in r.getMessage()]
    assert len(said) == 1 and "stamped 5000.0 s" in said[0], said
