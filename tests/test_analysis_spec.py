"""The spec `gyrocal analyze` writes carries the wander it found to the daemon's bias-state filter."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from gyrocal.analysis.extend import bias_spec
from gyrocal.cli import main
from gyrocal.datasets._common import data_dir
from gyrocal.model.bias_kalman import FLICKER_FLOOR, GM_PEAK, GM_PEAK_TAU, BiasKalman, BiasModel
from gyrocal.sim.truth import DPH


def _terms(b_dps: float, k: float, floor_tau_s: float) -> dict:
    """One axis of ``allan_terms``: the read-off's floor tau and the joint fit's B and K."""
    return {"bias_instability": {"value": 2 * b_dps, "tau_s": [floor_tau_s]},
            "joint_fit": {"bias_instability": {"value": b_dps}, "rate_random_walk": {"value": k}}}


def test_bias_spec_takes_the_joint_fit_on_wandering_axes_and_never_leaves_a_named_walk_empty() -> None:
    findings = [
        {"cause": "random_walk", "axes": ["x", "z"],
         "params": {"dps_per_sqrt_s": {"x": 7e-4, "z": 4e-3}, "allan_dps_per_sqrt_s": {"x": 9e-4, "z": 0.0}}},
        {"cause": "bias_instability", "axes": ["x", "y"], "params": {}},
        {"cause": "warmup", "axes": ["y"], "params": {}},
    ]
    allan = {"x": _terms(3e-3, 1e-4, 160.0), "y": _terms(2e-3, 5e-4, 80.0), "z": _terms(0.0, 0.0, 600.0)}
    spec = bias_spec(findings, allan)
    # the joint fit's K on a walk axis; z has neither K nor B in the fit: the finding's walk, the
    # test's REML intensity (not its Allan fit's walk part, 0 there); y is not a walk axis
    assert spec["random_walk"]["dps_per_sqrt_s"] == {"x": 1e-4, "z": 4e-3}
    bi = spec["bias_instability"]
    assert bi["dps"] == {"x": 3e-3, "y": 2e-3, "z": 0.0}  # the joint fit's B, not the read-off's
    assert bi["tau_s"]["x"] == 160.0 and bi["tau_s"]["y"] == 80.0 and bi["tau_s"]["z"] > 0
    m = BiasModel.from_spec(spec, "spec")
    np.testing.assert_allclose(m.random_walk_dps_per_sqrt_s, [1e-4, 0.0, 4e-3])
    np.testing.assert_allclose(m.gm_sigma_dps, FLICKER_FLOOR * np.array([3e-3, 2e-3, 0.0]) / GM_PEAK)
    np.testing.assert_allclose(m.gm_tau_s[:2], np.array([160.0, 80.0]) / GM_PEAK_TAU)
    # a NaN fit (too few taus) is no fit: the finding's walk
    allan["x"]["joint_fit"] = {"bias_instability": {"value": float("nan")},
                               "rate_random_walk": {"value": float("nan")}}
    assert bias_spec(findings, allan)["random_walk"]["dps_per_sqrt_s"]["x"] == 7e-4
    assert bias_spec([{"cause": "warmup", "axes": ["z"], "params": {}}], allan) == {}


def test_the_daemon_learns_with_the_wander_analyze_found_on_a_real_log(tmp_path: Path) -> None:
    """sunsided 10 min (MPU-6050, still): analyze names random_walk and a flicker floor
    (bias_instability) on x. The spec it writes, named as the daemon's kf terms file, gives the
    filter a Gauss-Markov state on x at the joint fit's floor (and its walk); z, which does not
    wander, gets none."""
    from gyrocal.daemon.config import load_config
    from gyrocal.daemon.learner import make_learner

    csv = tmp_path / "s10.csv"
    rec = data_dir("sunsided_mpu6050") / "unmoved-with-x-pointing-forward-10min"
    assert main(["convert", "sunsided", str(rec), str(csv)]) == 0
    out = tmp_path / "s10.json"
    assert main(["analyze", str(csv), "--json", str(out), "--quiet"]) == 0
    r = json.loads(out.read_text())
    found = {f["cause"]: f for f in r["findings"]}
    assert "x" in found["random_walk"]["axes"] and "x" in found["bias_instability"]["axes"]
    spec = Path(r["extended"]["spec_file"])
    doc = yaml.safe_load(spec.read_text())
    cfg = tmp_path / "kf.yaml"
    cfg.write_text(f"virtual_unit: {{enabled: true}}\nestimator: {{method: kf, terms: {spec.name}}}\n",
                   encoding="utf-8")
    learner = make_learner(load_config(cfg), None)
    assert isinstance(learner.est, BiasKalman)
    bias = learner.est.bias
    fit = r["allan_terms"]["x"]["joint_fit"]
    b_x, floor_tau = fit["bias_instability"]["value"], r["allan_terms"]["x"]["bias_instability"]["tau_s"][0]
    assert 2 * DPH < b_x < 50 * DPH and floor_tau >= 10.0  # a MEMS floor, at minutes, not seconds
    assert bias.gm_sigma_dps[0] == pytest.approx(FLICKER_FLOOR * b_x / GM_PEAK)
    assert bias.gm_tau_s[0] == pytest.approx(floor_tau / GM_PEAK_TAU)
    assert bias.random_walk_dps_per_sqrt_s[0] == pytest.approx(fit["rate_random_walk"]["value"])
    assert doc["bias_instability"]["dps"]["z"] == 0.0 and bias.gm_sigma_dps[2] == 0.0
    zero, one = np.zeros(200), np.ones(200)
    phi = learner.est.spec.design({"gx": zero, "gy": zero, "gz": one})  # still, z up
    learner.update_many(phi, np.full((200, 3), 0.01), np.arange(200) * 0.01)
    assert np.all(np.isfinite(learner.est.coefficients))
