"""A covariate effect is named as that covariate, not as random_walk (outside check H1, 2026-11-27).

DESIGN.md Contract 2 names ``random_walk`` only when no covariate explains the wander. The logs
here are white noise (0.05 deg/s per sample, 3 sessions x 180 s at 25 Hz, the 18-pose tumble) with
the simulator's default warm-up temperature course (+8 degC, tau 120 s), as ``gyrocal sim`` makes
them, and a temperature effect on x. Before the covariates were weighed against the walk with its
intensity re-estimated (``lrtest.test_against_walk``), both logs came out as random_walk x alone
(seeds 100-111 of the first: 9 / 12; of the second: 11 / 12, ``benchmarks/bench_covariate_walk.py``).
A walk still named where a covariate explains the wander lists it in ``confounded_with``. The
many-log figures are in docs/analysis.md ("Covariates weighed against the walk").
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from gyrocal.analysis.candidates import COVARIATE_CAUSES
from gyrocal.analysis.engine import analyze
from gyrocal.logformat import LogData

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_covariate_walk import white_log  # noqa: E402  (the benchmark's logs, one seed each here)


def _findings(cols: dict) -> dict[str, dict]:
    return {f["cause"]: f for f in analyze(LogData(cols, {}, [], "h1")).result["findings"]}


def test_a_temperature_effect_on_white_noise_is_named_a_covariate_not_random_walk() -> None:
    # before: random_walk x (LR p = 7e-11) and no covariate; temperature alone 26 % held out
    found = _findings(white_log(102, 0.003, 0.0, 0.0))
    assert "random_walk" not in found, found.keys()
    named = [c for c in COVARIATE_CAUSES if c in found]
    assert len(named) == 1 and found[named[0]]["axes"] == ["x"], found.keys()
    # on this course T, dT/dt and exp(-t_on / 120 s) have one shape: a look-alike must say so
    if named[0] != "temperature":
        assert "temperature" in found[named[0]]["params"]["confounded_with"]["x"]


def test_a_temperature_and_rate_pair_is_named_as_the_pair_not_random_walk() -> None:
    # with a 2 degC cycle the two covariates separate; before: random_walk x alone
    found = _findings(white_log(102, 0.003, 0.15, 2.0))
    assert "random_walk" not in found, found.keys()
    assert set(found) == {"temperature", "temperature_rate"}, found.keys()
    assert found["temperature"]["axes"] == ["x"] and found["temperature_rate"]["axes"] == ["x"]


def test_a_walk_named_where_a_covariate_explains_the_wander_says_so() -> None:
    # seed 107 is the pair set's borderline log: temperature_rate passes against the walk at
    # p = 5.7e-4, just above 0.01/18, and given it the walk is no longer significant; before, the
    # walk was named alone. Whichever side of the line the covariate falls, never random_walk alone.
    found = _findings(white_log(107, 0.003, 0.15, 2.0))
    covariates_on_x = [c for c in COVARIATE_CAUSES if c in found and "x" in found[c]["axes"]]
    if "random_walk" in found and not covariates_on_x:
        alike = found["random_walk"]["params"].get("confounded_with", {}).get("x", [])
        assert set(alike) & set(COVARIATE_CAUSES), found["random_walk"]["params"]
    assert covariates_on_x or "random_walk" in found


def test_a_warm_up_slower_than_the_test_grid_is_listed_as_the_named_rates_look_alike() -> None:
    # a 240 s warm-up (0.04 deg/s) + a temperature effect on x, 180 s sessions: the test's warm-up
    # grid stops at 90 s, so the warm-up cannot be named, and temperature_rate stands in for it;
    # before, temperature_rate x was named with no look-alike (a wrong cause, as the outside check's
    # gpair/warmup+temperature_0.15_white_7100). Now every covariate named on x that was not hidden
    # lists a hidden one (causes.covariate_look_alikes: it fits as well in its place)
    from gyrocal.analysis.hidden import inject

    found = _findings(inject(white_log(101, 0.003, 0.0, 2.0), "warmup", 0.04, ["x"], tau_s=240.0))
    hidden = {"warmup", "temperature"}
    named = [c for c in COVARIATE_CAUSES if c in found and "x" in found[c]["axes"]]
    assert named and "random_walk" not in found, found.keys()
    for c in named:
        if c not in hidden:
            alike = set(found[c]["params"].get("confounded_with", {}).get("x", []))
            assert hidden & alike, found[c]["params"]


def test_a_walk_named_as_a_warm_up_on_a_short_real_log_lists_the_walk() -> None:
    # benchmarks/inject_real.py's 0.6 sigma walk, variant 2 (seed 9), on mikoff imu2 y (160 s, one
    # session; sigma 0.0670 deg/s, so 0.6 x 0.0670 / sqrt(159.33 s / 2) = 0.0045 deg/s/sqrt(s)):
    # the warm-up passes against the walk by chi-square (p = 1.3e-5) and is named instead of the
    # walk, but against draws of the fitted walk null its D is common (p = 0.02): the finding must
    # say the log cannot tell it from a walk. Before: warmup y, no look-alike (a wrong cause).
    from gyrocal.analysis import causes, engine
    from gyrocal.analysis.candidates import all_candidates
    from gyrocal.analysis.hidden import inject
    from gyrocal.analysis.lrtest import build_axis_lr, test_against_walk
    from gyrocal.analysis.walkboot import calibrated_p
    from gyrocal.datasets._common import data_dir
    from gyrocal.datasets.mikoff import load_mikoff

    log = load_mikoff(data_dir("mikoff_mpu9150") / "imu2.log")
    cols = {k: np.array(v, float) for k, v in log.columns.items()}
    prob = engine.problem_of(inject(cols, "random_walk", 0.0045023, ["y"], seed=9))
    cands = all_candidates(prob)
    lr = build_axis_lr(prob, cands, 1)
    res = causes.select_axis(prob, 1, cands, 1.0, lr=lr)
    named = [s.cause for s in res.steps]
    alike = res.cov_alikes.get("warmup", [])
    assert "random_walk" in named or "random_walk" in alike, (named, res.cov_alikes)
    # the root cause: the chi-square reference is far too kind under a walk
    assert test_against_walk(lr, [], ("warmup",))[1] < 1e-4
    assert calibrated_p(lr, [], ("warmup",), 0.01, draws=1000) >= 0.01
