"""Simulation fidelity that sees every tau: measured Allan deviation against a simulated ensemble.

Why: one pooled curve over all sessions, compared with one simulated seed, hid long-tau misfit (a
10-minute session scored 0.28 decades alone and 0.05 pooled with five short ones). Here, per
session and per axis, the overlapping Allan deviation is taken at octave taus from 1/fs to a tenth
of the session's length, with a chi-square confidence interval, and compared with the median of an
ENSEMBLE of simulated logs (``ENSEMBLE`` seeds of the fitted model plus the error model). The
distance is the RMS over those taus of log10(measured / ensemble median) [decades]; the figure per
axis is the worst session. Stages: ``before`` (the baseline model with white noise at the
first-difference level: the simulation as it was), ``after`` (the extended model with the fitted
error model), and ``after`` without the colour or without the flicker bank (what each noise
extension is worth: the gain of ``coloured_noise`` and ``bias_instability``). Where a log's sessions
differ (recordings made on different days), each session is simulated under its own error model
(``session_models``).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from gyrocal.analysis.baseline import Problem
from gyrocal.analysis.noisemodel import NoiseModel, fit_twin, overlapping_avar, twin_chi2
from gyrocal.analysis.segments import AXES

ENSEMBLE = 8
"""Simulated logs per stage (fewer on logs over ``BIG_N`` samples, to keep the cost linear and small)."""
BIG_N = 200_000
LOW_TAU_FRACTION = 0.1
OWN_MIN_SAMPLES = 1024
"""A session needs this many samples for its own error model (octaves up to a tenth of it: 7)."""
OWN_ALPHA = 0.01
"""Level at which a log's sessions are found to differ on an axis (shared over its sessions)."""
METRIC = ("RMS over octave taus (1/fs .. session length / 10) of log10(measured / median of the "
          "simulated ensemble) Allan deviation, per session; per axis the worst session [decades]")


def session_taus(n: int) -> np.ndarray:
    """Octave cluster sizes [samples] from 1 to a tenth of n."""
    top = max(1, int(n * LOW_TAU_FRACTION))
    return 2 ** np.arange(int(np.floor(np.log2(top))) + 1)


def adev_ci(avar: np.ndarray, n: int, m: np.ndarray, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Confidence interval of an overlapping Allan deviation (chi-square, white-noise EDF)."""
    edf = np.maximum(1.0, (3.0 * (n - 1) / (2.0 * m)) - 2.0 * (n - 2) / n)
    edf = np.minimum(edf, n - 1.0)
    lo = np.sqrt(avar * edf / stats.chi2.ppf(0.5 + level / 2, edf))
    hi = np.sqrt(avar * edf / stats.chi2.ppf(0.5 - level / 2, edf))
    return lo, hi


def distance(measured: np.ndarray, simulated: np.ndarray) -> float:
    ok = np.isfinite(measured) & np.isfinite(simulated) & (measured > 0) & (simulated > 0)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(np.mean(np.log10(measured[ok] / simulated[ok]) ** 2)))


def fidelity_block(prob: Problem, fit_before: np.ndarray, fit_after: np.ndarray,
                   white_before: np.ndarray, models: list[NoiseModel], seed: int = 0) -> dict:
    """The ``fidelity`` key: per-session curves, ensemble medians and distances per stage."""
    sessions = np.unique(prob.usable.session)
    k_ens = ENSEMBLE if prob.n <= BIG_N else max(2, ENSEMBLE // 4)
    stages: dict[str, list[NoiseModel]] = {
        "before": [NoiseModel(prob.rate_hz, float(w) ** 2) for w in white_before],
        "after": models,
        "without_colour": [_drop(m, "colour") for m in models],
        "without_flicker": [_drop(m, "flicker") for m in models],
    }
    fits = {"before": fit_before, "after": fit_after, "without_colour": fit_after,
            "without_flicker": fit_after}
    out: dict = {"metric": METRIC, "ensemble": k_ens, "sessions": []}
    worst: dict[str, dict[str, float]] = {s: {} for s in stages}
    owns, out["session_models"] = session_models(prob, fit_after, models)
    for si, s in enumerate(sessions):
        sel = prob.usable.session == s
        n = int(sel.sum())
        m = session_taus(n)
        row: dict = {"session": int(s), "samples": n, "tau_s": (m / prob.rate_hz).round(6).tolist(),
                     "measured": {}, "ci_low": {}, "ci_high": {}}
        for k, a in enumerate(AXES):
            own = owns.get((si, k))
            smods = dict(stages)
            if own is not None:
                row.setdefault("own_model", {})[a] = own.to_dict()
                smods["after"] = list(models)
                smods["after"][k] = own
                smods["without_colour"] = [_drop(x, "colour") for x in smods["after"]]
                smods["without_flicker"] = [_drop(x, "flicker") for x in smods["after"]]
            av = overlapping_avar(prob.y[sel, k], m)
            lo, hi = adev_ci(av, n, m)
            meas = np.sqrt(av)
            row["measured"][a], row["ci_low"][a], row["ci_high"][a] = (
                meas.tolist(), lo.tolist(), hi.tolist())
            for st, mods in smods.items():
                rng = np.random.default_rng([seed, si, k, 0xF1D])
                ens = np.array([np.sqrt(overlapping_avar(fits[st][sel, k] + mods[k].simulate(n, rng), m))
                                for _ in range(k_ens)])
                med = np.median(ens, axis=0)
                if st in ("before", "after"):
                    row.setdefault(f"simulated_{st}", {})[a] = med.tolist()
                    row.setdefault(f"band_{st}", {})[a] = [np.min(ens, axis=0).tolist(),
                                                           np.max(ens, axis=0).tolist()]
                dist = distance(meas, med)
                row.setdefault(st, {})[a] = round(dist, 4)
                worst[st][a] = max(worst[st].get(a, 0.0), dist)
        out["sessions"].append(row)
    out["own_models"] = len(owns)
    for st, per_axis in worst.items():
        out[st] = {a: round(v, 4) for a, v in per_axis.items()}
    return out


def session_models(prob: Problem, fit_after: np.ndarray,
                   models: list[NoiseModel]) -> tuple[dict[tuple[int, int], NoiseModel], dict]:
    """Per-session error models on the axes where the log's sessions differ.

    Why: one log may hold recordings made on different days (sunsided: six), whose noise differs
    (sunsided z session 0 lies 0.10-0.13 decades below the pooled model at 0.6-2.6 s). Criterion, per
    axis: each session with at least ``OWN_MIN_SAMPLES`` samples tests the pooled model against its
    own Allan octaves (``twin_chi2``, about chi-square with one degree of freedom per octave when the
    model is right); the sessions differ when any of them rejects it at ``OWN_ALPHA`` shared over the
    sessions (Bonferroni). Then every such session gets ``fit_twin`` of its own residual (the pooled
    model's lines kept as candidates): one error model cannot serve them all, and a session that
    passes the pooled model by chance is still best described by its own. A log of one session, or
    whose sessions agree, keeps the pooled model. Returns ({(session index, axis): model}, figures).
    """
    sessions = np.unique(prob.usable.session)
    sels = [prob.usable.session == s for s in sessions]
    long = [i for i, sel in enumerate(sels) if sel.sum() >= OWN_MIN_SAMPLES]
    own: dict[tuple[int, int], NoiseModel] = {}
    info: dict = {}
    if len(sessions) < 2 or not long:
        return own, info
    for k, a in enumerate(AXES):
        chi, crit = [], []
        for i in long:
            c, dof = twin_chi2(models[k], prob.y[sels[i], k] - fit_after[sels[i], k])
            chi.append(round(c, 1))
            crit.append(round(float(stats.chi2.ppf(1.0 - OWN_ALPHA / len(long), max(dof, 1))), 1))
        differ = any(c > q for c, q in zip(chi, crit, strict=True))
        info[a] = {"sessions": [int(sessions[i]) for i in long], "chi2_pooled": chi, "critical": crit,
                   "differ": differ}
        if differ:
            lines = tuple((f, b) for f, b, _ in models[k].lines)
            for i in long:
                own[(i, k)] = fit_twin(prob.y[sels[i], k] - fit_after[sels[i], k], prob.rate_hz, lines)
    return own, info


def _drop(m: NoiseModel, what: str) -> NoiseModel:
    """The model less its colour (fast members and narrow-band lines; their variance goes to the white
    part, so the per-sample level stays) or less its flicker bank."""
    keep = m.slow if what == "colour" else m.fast
    white = m.white_var
    if what == "colour":
        white += sum(v for _, v in m.fast) + sum(v for _, _, v in m.lines)
    return NoiseModel(m.rate_hz, white, list(keep), m.walk_q, lines=[] if what == "colour" else list(m.lines))
