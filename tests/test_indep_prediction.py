"""The first push's predicted drift against the independent unit's truth, over many switch-ons.

Issue 9 asks that the drift predicted before the push be within 2x of the drift measured after
it, on a unit that is not gyrocal's own. A single axis's error is one draw of a weighted chi
variable, so even a prediction from the true covariance misses 2x now and then: over the unit's
own poses the exact figure landed within 2x on 90-97 % of axes (benchmarks/bench_indep.py
--inprocess, 40 seeds per rate). The unit's 24 poses are about half seen at the first push, so the
daemon's ``expected`` mixes its figure over the poses seen with one for the poses not seen yet,
in the share of rests at poses not seen yet, and ``bound`` (the worse of the poses seen and the
sphere) must bound the truth. Runs in process on the unit's own physics
(tests/indep/inprocess.py), about 1.5 s a switch-on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.indep.inprocess import first_push

SEEDS = range(1, 9)


def test_first_push_prediction_is_within_2x_and_the_gate_bounds_it(tmp_path: Path) -> None:
    after, expected, bound, cut = [], [], [], []
    for seed in SEEDS:
        r = first_push(tmp_path / str(seed), "fibre", 400.0, seed)
        assert r["pushed"], f"seed {seed}: no push"
        pred = r["predicted_drift_dph"]
        assert 0.0 < pred["unseen_share"] <= 1.0
        for a in "xyz":
            after.append(r["after"][a])
            expected.append(pred["expected"][a])
            bound.append(pred["bound"][a])
            # the gate's figure: between what is expected and the bound
            assert pred["expected"][a] <= pred["left"][a] * (1 + 1e-12)
            assert pred["left"][a] <= pred["bound"][a] * (1 + 1e-12)
            cut.append(r["before"][a] / r["after"][a])
    after, expected, bound = np.array(after), np.array(expected), np.array(bound)
    ratio = after / expected
    assert min(cut) >= 10.0, f"worst first-push cut {min(cut):.1f}x"
    within = np.mean((ratio >= 0.5) & (ratio <= 2.0))
    assert within >= 0.85, f"only {within:.0%} of axes within 2x of the prediction: {np.round(ratio, 2)}"
    # expected mixes the poses-seen and sphere figures: never above the worse of them
    assert np.all(expected <= bound * (1 + 1e-12))
    assert np.all(after <= 2.0 * bound), f"measured over the gate's bound: {np.round(after / bound, 2)}"
