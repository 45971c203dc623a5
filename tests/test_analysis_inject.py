"""Injections into a shipped real log (issue 12): the warm-up is tested with each axis' own tau."""

from __future__ import annotations

import numpy as np

from gyrocal.analysis.baseline import build_problem
from gyrocal.analysis.candidates import all_candidates
from gyrocal.analysis.hidden import inject
from gyrocal.analysis.holdout import ALPHA
from gyrocal.analysis.lrtest import AxisLR, build_axis_lr, search_factor
from gyrocal.analysis.segments import usable_samples
from gyrocal.datasets._common import data_dir
from gyrocal.datasets.tomisuarez import load_tomisuarez
from gyrocal.model.terms import derived_columns


def test_two_warmups_of_different_tau_are_each_tested_at_their_own_tau() -> None:
    """A fast warm-up on x (tau 5 s, 0.05 deg/s) beside a large slow one on y (tau 40 s, 0.4 deg/s),
    injected into the tomisuarez static log (100 s, 100 Hz). The candidate's pooled least-squares tau
    follows the large one (about 40 s), at which x's warm-up is not significant; the per-axis choice
    (the grid point with the largest likelihood ratio, paying a look-elsewhere factor of 9) finds
    5 s on x and names it."""
    log = load_tomisuarez(data_dir("tomisuarez_mpu6050") / "imu_static_test.csv")
    cols = inject(log.columns, "warmup", 0.05, ["x"], tau_s=5.0)
    cols = derived_columns(inject(cols, "warmup", 0.4, ["y"], tau_s=40.0))
    prob = build_problem(cols, usable_samples(cols))
    cands = all_candidates(prob)
    lrs = [build_axis_lr(prob, cands, k) for k in range(3)]
    assert [lr.warmup_tau_s for lr in lrs[:2]] == [5.0, 40.0]
    assert lrs[0].look_elsewhere["warmup"] == 9.0
    assert lrs[0].test([], "warmup")[1] < ALPHA
    assert lrs[1].test([], "warmup")[1] < ALPHA
    pooled = next(c for c in cands if c.cause == "warmup")
    assert pooled.info["tau_s"] > 20.0
    regs = [c for c in cands if c.cause != "random_walk" and c.full.shape[1]]
    old = AxisLR(prob, 0, {c.cause: c.full for c in regs},
                 {c.cause: search_factor(prob, c.cause) for c in regs})
    assert old.test([], "warmup")[1] > ALPHA  # what the pooled tau gave (p = 0.25)
    assert np.isfinite(lrs[2].test([], "warmup")[0])


def test_injection_scoring_counts_only_new_causes_as_wrong() -> None:
    """benchmarks/inject_real.py: what the cleaned log names itself is never wrong; a new regression
    cause is; the injected cause on another axis is a spill."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from inject_real import score

    own = {"x": ["periodic"], "y": [], "z": ["random_walk"]}
    found = {"x": ["periodic"], "y": ["warmup"], "z": ["random_walk"]}
    assert score(found, own, "warmup", "y", True) == {"named": True, "wrong": [], "spill": [],
                                                      "extra_walk": False}
    found = {"x": ["periodic", "temperature"], "y": ["random_walk"], "z": ["warmup", "random_walk"]}
    r = score(found, own, "warmup", "y", True)
    assert r == {"named": False, "wrong": ["temperature"], "spill": ["z"], "extra_walk": True}
    assert not score({"x": [], "y": ["periodic"], "z": []}, own, "periodic", "y", False)["named"]
