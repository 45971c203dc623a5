"""Write the extended model where the fitter and the daemon load it, and map it onto the truth model.

The spec file is YAML ``{terms: [...]}`` (the Contract 3 term names, loadable by ``gyrocal fit
--terms-file`` and the daemon). A random-walk finding is not a regression term: it is written as a
``random_walk`` block (the bias state's intensity per axis [deg/s/sqrt(s)]) for an estimator that
tracks the bias with a Kalman filter or with forgetting (seed 003); ``noise_model`` gives each axis'
fitted error model (white, colour and flicker Gauss-Markov members, walk) for a truth model or a
bias-state filter. Extra keys are information for people; loaders read ``terms``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from gyrocal.sim.truth import Effects, Thermal, TruthModel

AXES = ("x", "y", "z")


def write_spec(path: str | Path, result: dict, source: str = "") -> Path:
    """Write the extended model spec of an analysis result (Contract 2 dict) as YAML."""
    doc: dict = {"terms": list(result["extended"]["terms"])}
    doc["causes"] = {f["cause"]: {"axes": f["axes"], "params": _plain(f["params"])}
                     for f in result["findings"]}
    if result["extended"].get("random_walk"):
        doc["random_walk"] = _plain(result["extended"]["random_walk"])
    if result.get("noise_model"):  # per axis: white, colour and flicker bank (tau, SD), walk, ARW
        doc["noise_model"] = _plain(result["noise_model"])
    doc["source"] = f"gyrocal analyze {source}".strip()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text("# extended drift model written by gyrocal analyze; `terms` is the model spec\n"
                 + yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return p


def _plain(x):
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.floating | np.integer):
        return x.item()
    return x


def effects_from_findings(findings: list[dict]) -> Effects:
    """The truth-model Effects that reproduce the findings, so the re-run simulation matches.

    Warm-up, temperature rate, periodic, scale factor and random walk map one to one. The temperature
    finding maps onto the slope and curvature at its reference temperature [deg/s per degC].
    """
    e = Effects()

    def vec(d: dict) -> np.ndarray:
        return np.array([float(d.get(a, 0.0)) for a in AXES])

    for f in findings:
        p = f["params"]
        if f["cause"] == "temperature":
            e.temp_dps_per_c = vec(p["slope_dps_per_c"])
            e.temp2_dps_per_c2 = vec(p["curvature_dps_per_c2"])
            e.temp_ref_c = float(p["temp_ref_c"])
        elif f["cause"] == "temperature_rate":
            e.temp_rate_dps_per_cps = vec(p["dps_per_c_per_s"])
        elif f["cause"] == "warmup":
            e.warmup_dps, e.warmup_tau_s = vec(p["amplitude_dps"]), float(p["tau_s"])
        elif f["cause"] == "periodic":
            e.periodic_dps, e.periodic_hz = vec(p["amplitude_dps"]), float(p["frequency_hz"])
        elif f["cause"] == "scale_factor":
            e.scale_factor = vec(p["scale_factor"])
        elif f["cause"] == "random_walk":
            e.random_walk_dps_per_sqrt_s = vec(p["dps_per_sqrt_s"])
    return e


def truth_from_result(result: dict, thermal: Thermal | None = None) -> TruthModel:
    """A TruthModel with the baseline noise level and the found effects (coefficients default)."""
    noise = float(np.mean([result["noise_dps"][a] for a in AXES]))
    return TruthModel(noise_dps=noise, thermal=thermal or Thermal(),
                      effects=effects_from_findings(result["findings"]))
