"""Write the extended model where the fitter and the daemon load it, and map it onto the truth model.

The spec file is YAML ``{terms: [...]}`` (the Contract 3 term names, loadable by ``gyrocal fit
--terms-file`` and the daemon). A random-walk finding is not a regression term: it is written as a
``random_walk`` block (the bias state's intensity per axis [deg/s/sqrt(s)]) and a
``bias_instability`` block (the flicker floor B [deg/s] at tau_B [s]), which the daemon's ``kf``
estimator loads (``bias_spec``, ``BiasModel.from_spec``) to track the bias (seed 003);
``noise_model`` gives each axis' fitted error model (white, colour and flicker Gauss-Markov
members, walk) for a truth model or a bias-state filter. Extra keys are information for people;
loaders read ``terms``.
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
    doc.update(_plain(bias_spec(result["findings"], result["allan_terms"])))
    if result.get("noise_model"):  # per axis: white, colour and flicker bank (tau, SD), walk, ARW
        doc["noise_model"] = _plain(result["noise_model"])
    doc["source"] = f"gyrocal analyze {source}".strip()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text("# extended drift model written by gyrocal analyze; `terms` is the model spec\n"
                 + yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return p


def bias_spec(findings: list[dict], allan_terms: dict) -> dict:
    """The bias-state blocks the daemon's ``kf`` estimator reads (``BiasModel.from_spec``).

    Why: the filter has one walk and one Gauss-Markov state per axis, and needs their intensities
    at the time scales a push must hold (minutes), where the wander's Allan curve has its floor. The
    findings say which axes wander; the intensities come from the joint N, B, K fit of the residual's
    Allan curve (``allan_terms[axis].joint_fit``, the extended regressions' residual up to a tenth
    of the used span), as allan_variance_ros users read them. Before 2026-11-26 the spec carried the
    finding's walk alone, so a flicker floor never reached the filter, and mikoff imu1 y (walk part
    0) got no state at all. The finding's slow Gauss-Markov bank was tried in its place and did worse
    than no bias state: its floor sits at a few seconds, where the flicker acts as noise
    (``benchmarks/bench_bias_state.py``, docs/estimators.md).

    Per axis named random_walk or bias_instability:
    - ``bias_instability: {dps: B, tau_s: tau_B}``: B [deg/s] from the joint fit, tau_B [s] where
      the measured curve has its minimum (the IEEE read-off's tau); 0 on other axes;
    - ``random_walk.dps_per_sqrt_s`` [deg/s/sqrt(s)], random_walk axes only: the joint fit's K; where
      the fit gives the axis neither K nor B, the finding's ``dps_per_sqrt_s`` (the walk test's REML
      intensity), so a named wander never becomes an empty state.
    """
    by = {f["cause"]: f for f in findings}
    rw = by.get("random_walk")
    walk_axes = set(rw["axes"]) if rw else set()
    axes = walk_axes | set(by["bias_instability"]["axes"] if "bias_instability" in by else [])

    def fit(a: str, term: str) -> float:
        v = float(((allan_terms.get(a) or {}).get("joint_fit") or {}).get(term, {}).get("value", 0.0))
        return v if np.isfinite(v) and v > 0 else 0.0

    b_dps = {a: fit(a, "bias_instability") for a in axes}
    tau_b = {a: float(allan_terms[a]["bias_instability"]["tau_s"][0]) for a in axes if b_dps[a] > 0}
    out: dict = {}
    if rw is not None:
        p = rw["params"]
        walk = {}
        for a in rw["axes"]:
            walk[a] = fit(a, "rate_random_walk")
            if walk[a] <= 0 and b_dps[a] <= 0:  # the finding's walk: the test's (REML) intensity
                walk[a] = float(p.get("dps_per_sqrt_s", {}).get(a, 0.0))
        out["random_walk"] = {"dps_per_sqrt_s": walk}
    if tau_b:
        mean_tau = float(np.exp(np.mean(np.log(list(tau_b.values())))))
        out["bias_instability"] = {"dps": {a: b_dps.get(a, 0.0) for a in AXES},
                                   "tau_s": {a: tau_b.get(a, mean_tau) for a in AXES}}
    return out


def _plain(x):
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.floating | np.integer):
        return x.item()
    return x


def effects_from_findings(findings: list[dict], rate_hz: float | None = None) -> Effects:
    """The truth-model Effects that reproduce the findings, so the re-run simulation matches.

    Warm-up, temperature rate, periodic, scale factor and random walk map one to one. The temperature
    finding maps onto the slope and curvature at its reference temperature [deg/s per degC]. The noise
    causes map onto the truth model's noise: ``coloured_noise`` onto one Gauss-Markov rate
    (``gm_dps``, ``gm_tau_s``; see ``colour_to_truth``), ``bias_instability`` (or, without it, the
    flicker bank a ``random_walk`` finding carries) onto the flicker floor (``bias_instability_dps``,
    ``flicker_band_s``; see ``flicker_to_truth``); the narrow-band lines and resonances of
    ``coloured_noise`` (``params.lines``) onto ``Effects.lines`` (AR(2) noise). ``rate_hz`` [Hz] is
    the log's sample rate (the colour's correlation times are a few samples, so its discretisation
    matters); None treats the colour in continuous time.
    """
    e = Effects()

    def vec(d: dict) -> np.ndarray:
        return np.array([float(d.get(a, 0.0)) for a in AXES])

    flicker: dict | None = None
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
            # the Allan fit's walk, which goes with its flicker bank (the finding's dps_per_sqrt_s is
            # the test's REML walk, fitted without flicker: with the bank it would count the wander twice)
            e.random_walk_dps_per_sqrt_s = vec(p.get("allan_dps_per_sqrt_s", p["dps_per_sqrt_s"]))
            if flicker is None and p.get("flicker_bank"):
                flicker = {a: p["flicker_bank"][a] for a in f["axes"] if a in p["flicker_bank"]}
        elif f["cause"] == "coloured_noise":
            gm, e.gm_tau_s = colour_to_truth(p["gauss_markov"], rate_hz)
            e.gm_dps = vec(gm)
            e.lines = [(AXES.index(a), float(ln["frequency_hz"]), float(ln["half_width_hz"]),
                        float(ln["sd_dps"])) for a, ls in p.get("lines", {}).items() for ln in ls]
        elif f["cause"] == "bias_instability":
            flicker = p["flicker_bank"]
    if flicker:
        b, band = flicker_to_truth(flicker)
        if band is not None:
            e.bias_instability_dps, e.flicker_band_s = vec(b), band
    return e


def colour_to_truth(members: dict[str, list[dict]], rate_hz: float | None = None) -> tuple[dict, float]:
    """One Gauss-Markov rate per axis with a shared correlation time, from each axis' fitted colour.

    The truth model has one colour time constant for all axes. Per axis the fitted members (tau_s,
    sd_dps) give a per-sample variance V and a low-frequency (ARW) variance L = sum v (1 + phi) /
    (1 - phi); one first-order process with (1 + phi) / (1 - phi) = sum L / sum V matches both on
    average, and each axis' SD is then set so that its L (the long-tau Allan level) is exact.
    Returns ({axis: sd [deg/s]}, tau [s]).
    """
    def phi(t: float) -> float:
        return float(np.exp(-1.0 / (rate_hz * t))) if rate_hz else 0.0

    def lf(t: float) -> float:  # low-frequency variance per unit variance
        if rate_hz:
            return (1 + phi(t)) / (1 - phi(t))
        return 2.0 * t  # continuous time: PSD(0) = 2 v T, in units of one second
    v_tot, l_axis = 0.0, {}
    for a, ms in members.items():
        v = sum(float(m["sd_dps"]) ** 2 for m in ms)
        l_axis[a] = sum(float(m["sd_dps"]) ** 2 * lf(float(m["tau_s"])) for m in ms)
        v_tot += v
    if v_tot <= 0:
        return {a: 0.0 for a in members}, 0.1
    r = sum(l_axis.values()) / v_tot
    if rate_hz:
        ph = max((r - 1.0) / (r + 1.0), 1e-9)
        tau = -1.0 / (rate_hz * np.log(ph))
        k = (1 + ph) / (1 - ph)
    else:
        tau, k = r / 2.0, r
    return {a: float(np.sqrt(lv / k)) for a, lv in l_axis.items()}, float(tau)


def flicker_to_truth(bank: dict[str, list[dict]]) -> tuple[dict, tuple[float, float] | None]:
    """Bias instability B [deg/s] per axis and one flicker band [s] from each axis' slow GM bank.

    The truth model renders flicker as a flat Allan floor of 0.664 B over a band of taus. Per axis the
    bank's own Allan deviation (the slow members only) is evaluated on a fine tau grid; the band is
    where it stays within a factor sqrt(2) of its peak (the floor), joined over the axes, and B is
    the log-mean deviation over the band / 0.664. Returns ({axis: B}, (lo, hi)) or (.., None).
    """
    from gyrocal.model.allan import FLICKER_FLOOR, gauss_markov_avar

    all_t = [float(m["tau_s"]) for ms in bank.values() for m in ms]
    if not all_t:
        return {a: 0.0 for a in bank}, None
    taus = np.geomspace(min(all_t) / 10.0, max(all_t) * 10.0, 200)
    adev, lo, hi = {}, np.inf, 0.0
    for a, ms in bank.items():
        av = sum((gauss_markov_avar(taus, float(m["sd_dps"]), float(m["tau_s"])) for m in ms),
                 np.zeros_like(taus))
        if not np.any(av > 0):
            continue
        adev[a] = np.sqrt(av)
        inband = taus[adev[a] >= adev[a].max() / np.sqrt(2.0)]
        lo, hi = min(lo, float(inband[0])), max(hi, float(inband[-1]))
    if not adev or not hi > lo:
        return {a: 0.0 for a in bank}, None
    sel = (taus >= lo) & (taus <= hi)
    b = {a: float(np.exp(np.mean(np.log(d[sel]))) / FLICKER_FLOOR) for a, d in adev.items()}
    return b, (lo, hi)


def truth_from_result(result: dict, thermal: Thermal | None = None) -> TruthModel:
    """A TruthModel with the log's noise and the found effects (coefficients default).

    The white level is one number in the truth model: the mean over axes of the white part of the
    fitted error model where coloured_noise is named (its colour goes to ``gm_dps``), else of the
    per-sample noise (``noise_dps``).
    """
    rate = result.get("samples", {}).get("rate_hz")
    effects = effects_from_findings(result["findings"], rate)
    colour = next((f for f in result["findings"] if f["cause"] == "coloured_noise"), None)
    white = []
    for a in AXES:
        if colour is not None and a in colour["axes"] and "white_dps" in colour["params"]:
            white.append(float(colour["params"]["white_dps"][a]))
        else:
            white.append(float(result["noise_dps"][a]))
    return TruthModel(noise_dps=float(np.mean(white)), thermal=thermal or Thermal(), effects=effects)
