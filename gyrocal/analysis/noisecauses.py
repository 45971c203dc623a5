"""The two noise causes, ``coloured_noise`` and ``bias_instability``: named by the Allan fit, valued
by fidelity.

Why separate from the regression causes: neither can be predicted, so neither lowers the held-out
error; what they change is how well the simulation reproduces the sensor (DESIGN.md Contract 2).
A component is named when (1) leaving it out of the error model's Allan-variance fit costs at least
``NEED_MIN`` in weighted misfit (white noise alone gives about 0-2; a DLPF-coloured MPU-9150 gives
hundreds), and (2) adding it to the simulation brings the measured and simulated Allan deviation
closer by at least ``GAIN_MIN`` decades on the axis' worst session (the fidelity gain).
"""

from __future__ import annotations

import numpy as np

from gyrocal.analysis.baseline import Problem
from gyrocal.analysis.candidates import gridded, spectrum
from gyrocal.analysis.diagnostics import autocorrelation
from gyrocal.analysis.noisemodel import NoiseModel, component_need
from gyrocal.analysis.segments import AXES

NEED_MIN = 30.0
GAIN_MIN = 0.02
LINE_RATIO = 8.0
"""A narrow-band line: the residual spectrum, smoothed over ``LINE_SMOOTH_HZ``, peaks at this many times
the median of each of its flanks (0.25-2 Hz either side; the higher flank counts, so a slope is not a
line). White noise: the largest smoothed bin of thousands is about 2x its neighbours."""
LINE_SMOOTH_HZ = 0.05
MAX_LINES = 3
"""Lines per axis: the strongest first, then the next outside +-``LINE_EXCLUDE_HZ`` of those found
(mikoff imu1 / imu4 z: a 35.5-35.7 Hz line beside the stronger periodic one)."""
LINE_EXCLUDE_HZ = 1.0
LINE_MIN_HZ = 1.0
"""Lines below this are left to the slow states (flicker, walk) and the periodic cause."""
TEST = ("Allan-variance fit of the error model with and without the component (weighted misfit "
        f"increase >= {NEED_MIN:g}) and simulated-ensemble fidelity gain >= {GAIN_MIN} decades")


def noise_findings(prob: Problem, resid: np.ndarray, models: dict[str, NoiseModel], fid: dict) -> list[dict]:
    """Contract 2 findings for the noise causes (explained_fraction 0: they explain no held-out error)."""
    need = {a: component_need(resid[:, k], prob.rate_hz, tuple((f, b) for f, b, _ in models[a].lines))
            for k, a in enumerate(AXES)}
    out = []
    for cause, comp, stage in (("coloured_noise", "colour", "without_colour"),
                               ("bias_instability", "flicker", "without_flicker")):
        axes, gains = [], {}
        for a in AXES:
            gain = fid[stage][a] - fid["after"][a]
            gains[a] = round(gain, 4)
            if need[a][comp] >= NEED_MIN and gain >= GAIN_MIN:
                axes.append(a)
        if not axes:
            continue
        params: dict = {"fidelity_gain_decades": {a: gains[a] for a in axes},
                        "allan_fit_need": {a: round(need[a][comp], 1) for a in axes}}
        if cause == "coloured_noise":
            params["acf_lag1"] = {a: round(float(autocorrelation(resid[:, AXES.index(a)], 1)[0]), 3)
                                  for a in axes}
            params["gauss_markov"] = {a: [{"tau_s": t, "sd_dps": float(np.sqrt(v))}
                                          for t, v in models[a].fast]
                                      for a in axes}
            params["white_dps"] = {a: float(np.sqrt(models[a].white_var)) for a in axes}
            lines = {a: [{"frequency_hz": f, "half_width_hz": b, "sd_dps": float(np.sqrt(v))}
                         for f, b, v in models[a].lines] for a in axes if models[a].lines}
            if lines:  # narrow-band noise (a wandering resonance), part of the colour
                params["lines"] = lines
            what = "a short Gauss-Markov (low-pass) colour"
        else:
            params["flicker_bank"] = {a: [{"tau_s": t, "sd_dps": float(np.sqrt(v))}
                                          for t, v in models[a].slow]
                                      for a in axes}
            params["bias_instability_dps"] = {a: _floor(models[a]) for a in axes}
            what = "a flicker floor (a bank of slow Gauss-Markov processes)"
        worst = max(axes, key=lambda a: gains[a])
        out.append({
            "cause": cause, "axes": axes, "explained_fraction": 0.0, "p_value": None, "test": TEST,
            "params": params,
            "evidence": (f"On axes {', '.join(axes)}, the measured Allan deviation needs {what}: "
                         f"adding it to the simulation moves the ensemble {gains[worst]:.2f} decades "
                         f"closer on axis {worst} (fidelity {fid[stage][worst]:.2f} -> "
                         f"{fid['after'][worst]:.2f})."),
        })
    return out


def find_lines(prob: Problem, resid: np.ndarray) -> list[tuple[tuple[float, float], ...]]:
    """Per axis, up to ``MAX_LINES`` narrow-band lines of the residual (M, 3), strongest first, as
    ((centre, half width) [Hz], ...), or () when there is none (see ``LINE_RATIO``).

    Why: a resonance whose frequency wanders (sunsided z, 31.4 Hz, 30 % of the variance) is not one
    sinusoid, so the periodic cause explains too little of it; as noise it is a second-order
    Gauss-Markov line (``NoiseModel.lines``) that the simulation must reproduce. The centre and the
    half width are the mean and the SD of the power above the flank level within 0.25 Hz of the peak.
    """
    grids = gridded(prob, resid, np.ones(prob.n, dtype=bool))
    if not grids:
        return [(), (), ()]
    f, p = spectrum(prob, grids)
    df = float(f[1] - f[0])
    w = max(1, int(round(LINE_SMOOTH_HZ / df)))
    sm = np.apply_along_axis(lambda c: np.convolve(c, np.ones(w) / w, mode="same"), 0, p)
    band = np.flatnonzero((f >= LINE_MIN_HZ) & (f <= 0.45 * prob.rate_hz))
    out: list[tuple[tuple[float, float], ...]] = []
    for k in range(resid.shape[1]):
        found: list[tuple[float, float]] = []
        free = band.copy()
        while band.size >= 100 and len(found) < MAX_LINES and free.size:
            j = int(free[np.argmax(sm[free, k])])
            d = f - f[j]
            flanks = [sm[(d >= -2.0) & (d <= -0.25) & (f > 0), k], sm[(d >= 0.25) & (d <= 2.0), k]]
            flanks = [x for x in flanks if x.size >= 10]
            ref = max((float(np.median(x)) for x in flanks), default=0.0)
            if ref <= 0 or sm[j, k] / ref < LINE_RATIO:
                break
            win = np.abs(d) <= 0.25
            ex = np.maximum(p[win, k] - ref, 0.0)
            c = float(np.sum(f[win] * ex) / np.sum(ex))
            hw = float(np.sqrt(np.sum((f[win] - c) ** 2 * ex) / np.sum(ex)))
            found.append((round(c, 4), round(max(hw, df), 4)))
            free = free[np.abs(f[free] - c) > LINE_EXCLUDE_HZ]
        out.append(tuple(found))
    return out


def _floor(m: NoiseModel) -> float:
    """The minimum of the model's Allan deviation over the bank's taus [deg/s] (the read-off floor)."""
    mm = 2.0 ** np.arange(0, 26)
    return float(np.sqrt(np.min(m.avar(mm))))
