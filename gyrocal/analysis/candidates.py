"""Candidate causes: for each word of the Contract 2 vocabulary, the extra design columns it adds.

Every nonlinear choice (a warm-up time constant, a periodic frequency) is made on the training folds
only, so the held-out test is honest. A candidate that its inputs cannot support (no temperature
column, a flat temperature, no reference rates) is not offered.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from gyrocal.analysis.baseline import Problem, gram_solve, lstsq
from gyrocal.analysis.segments import AXES
from gyrocal.model.terms import TermSpec

WARMUP_TAUS_S = (5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0, 640.0)
"""Grid of warm-up time constants [s]; the grid is cut at the longest session."""


@dataclass
class Candidate:
    """One cause's extra columns: per fold (chosen on training data) and on all data."""

    cause: str
    folds: list[np.ndarray]  # per fold, (M, p)
    full: np.ndarray  # (M, p), chosen on all data
    terms: list[str]  # Contract 3 term names of ``full`` ([] for the random-walk state)
    info: dict = field(default_factory=dict)  # e.g. frequency_hz, tau_s, knot_s
    tau_s: float | None = None  # averaging time the test needs (periodic), None = global
    covariate: str = "t"  # what to plot the residual against
    n_params: int = 0
    penalty: np.ndarray | None = None  # (R, p) rows appended as "penalty @ coef = 0" (smoothness)


def _terms_design(prob: Problem, names: list[str]) -> np.ndarray:
    return TermSpec.parse(names).design(prob.cols)


def temperature(prob: Problem) -> Candidate | None:
    """Bias on the temperature level: T and T^2 (seed 004's static inputs)."""
    if "temp" not in prob.cols or np.std(prob.cols["temp"]) < 0.05:
        return None
    names = ["temp", "temp^2"]
    x = _terms_design(prob, names)
    return Candidate("temperature", [x] * prob.n_folds, x, names, covariate="temp", n_params=2)


def temperature_rate(prob: Problem) -> Candidate | None:
    """Bias on the temperature rate: dT/dt and T*dT/dt (seed 004's dynamic inputs)."""
    if "temp" not in prob.cols or np.std(prob.cols.get("dtemp", np.zeros(1))) < 1e-4:
        return None
    names = ["dtemp", "temp*dtemp"]
    x = _terms_design(prob, names)
    return Candidate("temperature_rate", [x] * prob.n_folds, x, names, covariate="dtemp", n_params=2)


def _best_tau(prob: Problem, train: np.ndarray, taus: list[float]) -> float:
    """The warm-up time constant [s] that best fits the training samples (pooled over axes).

    A grid search, then a bounded refinement in log(tau) around the best grid point, so a time
    constant between grid points does not leave a structured misfit behind.
    """
    # Frisch-Waugh: the baseline is fitted once; each tau only projects its one column out of it
    # (O(M P) per tau instead of a fresh O(M P^2) least squares; the warm-up search was a fifth of
    # the analysis of a 3-hour log)
    base, y, t_on = prob.base[train], prob.y[train], prob.cols["t_on"][train]
    g_bb = base.T @ base
    beta_b, _ = lstsq(base, y)
    r = y - base @ beta_b
    rr = float(np.sum(r * r))

    def sse(tau: float) -> float:
        e = np.exp(-t_on / tau)
        e_r = e - base @ gram_solve(g_bb, base.T @ e, base.shape[0])
        ee = float(e_r @ e_r)
        if ee <= 1e-12 * float(e @ e):  # the warm-up lies in the baseline's span: it explains nothing
            return rr
        er = e_r @ r
        return rr - float(np.sum(er * er)) / ee

    best = min(taus, key=sse)
    res = optimize.minimize_scalar(lambda lt: sse(float(np.exp(lt))), method="bounded",
                                   bounds=(np.log(best / 2), np.log(best * 2)), options={"xatol": 0.02})
    return float(np.exp(res.x)) if res.fun < sse(best) else best


def warmup(prob: Problem) -> Candidate | None:
    """An exponential transient after each switch-on, exp(-t_on / tau)."""
    t_max = float(np.max(prob.cols["t_on"]))
    taus = [t for t in WARMUP_TAUS_S if t <= t_max / 2] or [WARMUP_TAUS_S[0]]
    folds = []
    for k in range(prob.n_folds):
        tau = _best_tau(prob, prob.fold != k, taus)
        folds.append(np.exp(-prob.cols["t_on"] / tau)[:, None])
    tau = float(f"{_best_tau(prob, np.ones(prob.n, dtype=bool), taus):.3g}")
    name = f"exp(-t_on/{tau:g})"
    return Candidate("warmup", folds, _terms_design(prob, [name]), [name], {"tau_s": tau},
                     covariate="t_on", n_params=1)


DETREND_S = 10.0
"""Window [s] of the local mean removed before the spectrum, so slow drift does not leak."""
F_MIN_HZ = 0.15
"""Lowest frequency [Hz] the periodic search considers; slower content belongs to the other causes."""


def gridded(prob: Problem, resid: np.ndarray, mask: np.ndarray) -> list[np.ndarray]:
    """Per session, the residual (M, K) on its regular time grid, locally detrended, zero in gaps.

    The local mean over ``DETREND_S`` is a normalised convolution (sum of the samples present over
    their count), so the gaps of a tumble do not bias it. Without it, a slow drift, cut into pieces
    by the still mask, leaks into the mask's own harmonics (0.5 Hz for a 2 s pose cycle).
    """
    fs = prob.rate_hz
    t = prob.cols["t"]
    r2 = resid.reshape(resid.shape[0], -1)
    out = []
    half = max(1, int(round(DETREND_S * fs / 2)))
    for s in np.unique(prob.usable.session):
        m = (prob.usable.session == s) & mask
        if m.sum() < 16:
            continue
        i = np.round((t[m] - t[m][0]) * fs).astype(int)
        n = int(i.max()) + 1
        g = np.zeros((n, r2.shape[1]))
        w = np.zeros(n)
        g[i], w[i] = r2[m], 1.0
        cg = np.vstack([np.zeros((1, g.shape[1])), np.cumsum(g, axis=0)])
        cw = np.concatenate(([0.0], np.cumsum(w)))
        lo = np.clip(np.arange(n) - half, 0, n)
        hi = np.clip(np.arange(n) + half + 1, 0, n)
        local = (cg[hi] - cg[lo]) / np.maximum(cw[hi] - cw[lo], 1.0)[:, None]
        out.append((g - local) * w[:, None])
    return out


def spectrum(prob: Problem, grids: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Frequencies [Hz] and power (F, K) summed over sessions, zero-padded to a common length."""
    nfft = 1 << int(np.ceil(np.log2(2 * max(len(g) for g in grids))))
    power = sum(np.abs(np.fft.rfft(g, n=nfft, axis=0)) ** 2 for g in grids)
    return np.fft.rfftfreq(nfft, 1.0 / prob.rate_hz), power


def peak_frequency_hz(prob: Problem, resid: np.ndarray, mask: np.ndarray) -> float:
    """Frequency [Hz] of the largest spectral peak of the residual (M, 3) on ``mask``.

    The residual is placed on each session's regular time grid with zeros in the gaps (moves,
    held-out blocks), so the phase of a disturbance that runs on absolute time is kept; the power is
    summed over axes and sessions.
    """
    grids = gridded(prob, resid, mask)
    if not grids:
        return float("nan")
    f, p = spectrum(prob, grids)
    power = p.sum(axis=1)
    band = (f >= F_MIN_HZ) & (f <= 0.45 * prob.rate_hz)
    if not band.any():
        return float("nan")
    k = int(np.flatnonzero(band)[np.argmax(power[band])])
    if 0 < k < len(power) - 1:  # parabolic refinement on log power
        a, b, c = np.log(power[k - 1 : k + 2] + 1e-300)
        den = a - 2 * b + c
        shift = 0.5 * (a - c) / den if den != 0 else 0.0
        return float(f[k] + np.clip(shift, -0.5, 0.5) * (f[1] - f[0]))
    return float(f[k])


def _sincos(prob: Problem, f_hz: float) -> np.ndarray:
    w = 2 * np.pi * f_hz * prob.cols["t"]
    return np.column_stack([np.sin(w), np.cos(w)])


def periodic(prob: Problem) -> Candidate | None:
    """A sinusoid at the residual's spectral peak: sin(2 pi F t), cos(2 pi F t)."""
    folds = []
    for k in range(prob.n_folds):
        train = prob.fold != k
        beta, _ = lstsq(prob.base[train], prob.y[train])
        f = peak_frequency_hz(prob, prob.y - prob.base @ beta, train)
        folds.append(_sincos(prob, f) if np.isfinite(f) else np.zeros((prob.n, 2)))
    beta, _ = lstsq(prob.base, prob.y)
    f = peak_frequency_hz(prob, prob.y - prob.base @ beta, np.ones(prob.n, dtype=bool))
    if not np.isfinite(f):
        return None
    f = round(f, 4)
    names = [f"sin({f:g})", f"cos({f:g})"]
    return Candidate("periodic", folds, _terms_design(prob, names), names, {"frequency_hz": f},
                     tau_s=min(1.0, 0.25 / f), covariate="phase", n_params=2)


def scale_factor(prob: Problem) -> Candidate | None:
    """An error proportional to the true rate: the reference rates as regressors (scale + cross)."""
    if not prob.usable.with_reference:
        return None
    names = [f"ref_w{a}" for a in AXES]
    x = _terms_design(prob, names)
    if np.max(np.abs(x)) == 0:
        return None
    return Candidate("scale_factor", [x] * prob.n_folds, x, names, covariate="ref_w", n_params=3)


def random_walk(prob: Problem) -> Candidate:
    """A wandering bias: no regression columns; the slow states of the error model (walk, flicker
    bank), tracked by a Kalman smoother (``lrtest.heldout_walk``), seed 003's bias state."""
    empty = np.zeros((prob.n, 0))
    return Candidate("random_walk", [empty] * prob.n_folds, empty, [], {}, covariate="t")


BUILDERS = (temperature, temperature_rate, warmup, periodic, scale_factor, random_walk)
COVARIATE_CAUSES = ("temperature", "temperature_rate", "warmup")


def all_candidates(prob: Problem) -> list[Candidate]:
    out = []
    for build in BUILDERS:
        c = build(prob)
        if c is not None:
            out.append(c)
    return out
