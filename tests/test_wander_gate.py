"""The push gate on a unit whose bias wanders (refine.py's floor), end to end in simulated time.

Why: on a tactical MEMS unit with a bias random walk and a flicker floor, the gate's plain rule (the
predicted drift left below 1/20 of the drift removed) needs hours of rests, and the daemon left the
unit uncalibrated meanwhile. With the ``kf`` estimator and the spec ``gyrocal analyze`` writes, the
daemon knows how far the wander moves the bias over the next ``push.wander_horizon_s``; once learning
longer cannot buy much against that, and the push cuts the total, it pushes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from gyrocal.daemon.config import load_config
from gyrocal.daemon.session import Session
from gyrocal.daemon.store import CalibrationStore
from gyrocal.model.terms import SEED000_TERMS
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import DPH, Effects, TruthModel
from gyrocal.sim.unit import VirtualUnit
from tests.daemon_harness import RATE_HZ, Harness

NOISE_DPS = 0.1   # per sample at 400 Hz: ARW 0.3 deg/sqrt(h)
WALK = 1e-4       # deg/s/sqrt(s): 21.6 deg/h/sqrt(h)
B_DPS = 10 * DPH  # bias instability 10 deg/h


def test_a_wandering_mems_unit_is_calibrated_where_the_plain_rules_would_wait(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A unit with 16-46 deg/h of switch-on bias and gravity drift over its poses, a walk and a flicker
    floor; kf with the true intensities. It is pushed within 10 minutes of tumbling, at a moment when
    both plain rules still refuse: the gate's (left x 20 > removed on some axis) and validation's (the
    held-out RMS falls by less than 20 %, the wander and the noise being in every block). The paired
    gain on the recent held-out blocks is significant instead, and the unit's systematic drift falls
    >= 2x per axis. (rls on such units: no push in 1200 s, benchmarks/bench_wander_gate.py.)

    Validation's plain rule is taken here over all the held-out blocks: with its trim (the quarter of
    blocks neither set explains left out, ``Session.VALIDATION_TRIM``) the quieter blocks show the
    gain on this unit and the plain rule passes too, which would leave the wander's path untested."""
    monkeypatch.setattr(Session, "VALIDATION_TRIM", 0.0)
    spec = tmp_path / "unit.terms.yaml"
    spec.write_text(yaml.safe_dump({"terms": list(SEED000_TERMS), "random_walk": {"dps_per_sqrt_s": WALK},
                                    "bias_instability": {"dps": B_DPS, "tau_s": 300.0}}), encoding="utf-8")
    cfg = load_config(None, {"state_dir": str(tmp_path / "state"), "control_socket": str(tmp_path / "c.sock"),
                             "estimator": {"method": "kf", "terms": str(spec),
                                           "convergence": {"max_change_dps": 5e-3, "max_sigma_dps": 2e-3,
                                                           "window": 5000}}})
    effects = Effects(random_walk_dps_per_sqrt_s=np.full(3, WALK), bias_instability_dps=np.full(3, B_DPS),
                      flicker_band_s=(1.0, 3000.0))
    truth = TruthModel(noise_dps=NOISE_DPS, effects=effects, switch_on_bias_dps=54 * DPH)
    unit = VirtualUnit(truth, tumble(1.2, 0.4), RATE_HZ, 1, 4242)
    h = Harness(cfg, unit, CalibrationStore(cfg.state_dir))
    h.switch_on()
    h.run(600, until=lambda h: h.session is not None and bool(h.session.last_push))
    s = h.session
    assert s is not None and s.last_push.get("status") == "acked", s.reason
    pred = s.last_push["predicted_drift_dph"]
    left, removes = np.array(list(pred["left"].values())), np.array(list(pred["removes"].values()))
    assert np.any(left * cfg.push["min_cut"] > removes), (left, removes)  # the plain gate would wait
    v = s.last_validation
    old2 = sum(x**2 for x in v["rms_current_dps"].values())
    new2 = sum(x**2 for x in v["rms_new_dps"].values())
    assert new2 > 0.8**2 * old2  # the plain validation would refuse this set
    assert v["passed"] and v["wander"]["gain_z"] >= 3.0
    assert h.store.latest(unit.serial) is not None
    st = unit.status()
    for a in "xyz":
        assert st["drift_rms_compensated_dps"][a] * 2 <= st["drift_rms_raw_dps"][a], a
