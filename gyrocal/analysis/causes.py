"""Name the cause: forward selection of candidate causes on held-out data, per axis.

Per axis, starting from the baseline, the candidate that most reduces the held-out, tau-averaged
residual variance is added, as long as it passes the significance rule of ``holdout`` (the minimum
share applies to the variance the model so far leaves, so a small second effect is still found). The random
walk is flexible enough to mimic any slow effect, so (DESIGN.md) it is chosen only when no covariate
cause (temperature, its rate, warm-up) explains about as well (``RW_COVARIATE_SHARE``,
``RW_LEFTOVER_RATIO``) with its one or two parameters against the walk's one per knot.
Findings merge the axes on which a cause was selected and are ranked by the share of the baseline
held-out variance they explain (their incremental reduction, so the shares add up).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from gyrocal.analysis.baseline import Problem
from gyrocal.analysis.candidates import COVARIATE_CAUSES, Candidate
from gyrocal.analysis.holdout import (
    ALPHA,
    MIN_FRACTION,
    MIN_FRACTION_OF_BASELINE,
    compare,
    heldout_residual,
    moving_average,
    penalized_lstsq,
    tau_window,
)
from gyrocal.analysis.segments import AXES

RW_COVARIATE_SHARE = 0.8
RW_LEFTOVER_RATIO = 2.0
"""A covariate explains the wander "about as well" as the random walk when it explains at least
RW_COVARIATE_SHARE of what the walk explains and leaves at most RW_LEFTOVER_RATIO times its leftover."""
MAX_CAUSES_PER_AXIS = 3


@dataclass
class Step:
    cause: str
    fraction: float  # incremental share of baseline held-out variance (at the candidate's tau)
    p_value: float
    blocks: int


@dataclass
class AxisResult:
    """The selected causes of one axis and its held-out residuals."""

    steps: list[Step] = field(default_factory=list)
    first: dict[str, dict] = field(default_factory=dict)  # every candidate against the baseline
    r_base: np.ndarray | None = None
    r_ext: np.ndarray | None = None


def _ms(prob: Problem, r: np.ndarray, tau_s: float) -> float:
    v, _ = moving_average(r, prob.usable.run, tau_window(prob, tau_s))
    return float(np.mean(v**2)) if v.size else float("nan")


def select_axis(
    prob: Problem, axis: int, cands: list[Candidate], tau_s: float,
    progress: Callable[[str], None] | None = None, cache: dict | None = None,
) -> AxisResult:
    """Forward selection of causes on one axis (see the module docstring for the rule).

    ``cache`` maps a tuple of cause names to held-out residuals (M, 3), shared between axes: the
    models are the same on every axis until the axes' selections differ.
    """
    cache = {} if cache is None else cache

    def heldout(models: list[Candidate]) -> np.ndarray:
        key = tuple(c.cause for c in models)
        if key not in cache:
            extras = [[c.folds[k] for c in models] for k in range(prob.n_folds)]
            cache[key] = heldout_residual(prob, extras, [c.penalty for c in models])
        return cache[key][:, axis]

    res = AxisResult()
    res.r_base = heldout([])
    chosen: list[Candidate] = []
    r_cur = res.r_base
    while len(chosen) < MAX_CAUSES_PER_AXIS:
        scored = []
        for c in cands:
            if c in chosen:
                continue
            r_new = heldout([*chosen, c])
            tau_c = c.tau_s if c.tau_s is not None else tau_s
            cmp = compare(prob, r_cur, r_new, tau_c)
            frac = cmp.reduction / _ms(prob, res.r_base, tau_c)
            of_left = cmp.reduction / _ms(prob, r_cur, tau_c)
            scored.append((c, frac, cmp, r_new, of_left))
        if not chosen:
            res.first = {s[0].cause: {"explained_fraction": round(float(s[1]), 4), "p_value": s[2].p_value}
                         for s in scored}
        sig = [s for s in scored if s[2].p_value < ALPHA and s[4] >= MIN_FRACTION
               and s[1] >= MIN_FRACTION_OF_BASELINE]
        if not sig:
            break
        best = max(sig, key=lambda s: s[1])
        if best[0].cause == "random_walk":
            alt = [s for s in scored if s[0].cause in COVARIATE_CAUSES and s[2].p_value < ALPHA
                   and s[1] >= RW_COVARIATE_SHARE * best[1]
                   and 1.0 - s[1] <= RW_LEFTOVER_RATIO * (1.0 - best[1])]
            if alt:
                best = max(alt, key=lambda s: s[1])
        c, frac, cmp, r_new, _ = best
        chosen.append(c)
        res.steps.append(Step(c.cause, float(frac), cmp.p_value, cmp.blocks))
        r_cur = r_new
        if progress:
            progress(f"axis {AXES[axis]}: {c.cause} explains {frac:.1%} (p={cmp.p_value:.2g})")
    res.r_ext = r_cur
    return res


def fit_full(prob: Problem, axis: int, chosen: list[Candidate]) -> tuple[np.ndarray, np.ndarray]:
    """Fit baseline + chosen causes on all used samples: (coefficients, in-sample residual)."""
    x = np.column_stack([prob.base, *(c.full for c in chosen)])
    beta = penalized_lstsq(x, prob.y[:, axis], [c.full for c in chosen], [c.penalty for c in chosen])
    return beta, prob.y[:, axis] - x @ beta


def cause_coefficients(prob: Problem, chosen: list[Candidate], beta: np.ndarray) -> dict[str, np.ndarray]:
    """Slice the coefficient vector into each chosen cause's coefficients."""
    out, k = {}, prob.base.shape[1]
    for c in chosen:
        p = c.full.shape[1]
        out[c.cause] = beta[k : k + p]
        k += p
    return out


def cause_params(prob: Problem, cand: Candidate, coefs: dict[str, np.ndarray]) -> dict:
    """The physical parameters of a cause from its per-axis coefficients (axis -> array)."""
    p: dict = dict(cand.info)
    if cand.cause == "temperature":
        t_ref = float(np.mean(prob.cols["temp"]))
        p["temp_ref_c"] = round(t_ref, 3)
        p["slope_dps_per_c"] = {a: float(b[0] + 2 * b[1] * t_ref) for a, b in coefs.items()}
        p["curvature_dps_per_c2"] = {a: float(b[1]) for a, b in coefs.items()}
    elif cand.cause == "temperature_rate":
        t_ref = float(np.mean(prob.cols["temp"]))
        p["dps_per_c_per_s"] = {a: float(b[0] + b[1] * t_ref) for a, b in coefs.items()}
        p["temp_ref_c"] = round(t_ref, 3)
    elif cand.cause == "warmup":
        p["amplitude_dps"] = {a: float(b[0]) for a, b in coefs.items()}
    elif cand.cause == "periodic":
        p["amplitude_dps"] = {a: float(np.hypot(b[0], b[1])) for a, b in coefs.items()}
    elif cand.cause == "scale_factor":
        p["scale_factor"] = {a: float(b[AXES.index(a)]) for a, b in coefs.items()}
        p["cross_coupling"] = {a: [float(v) for v in b] for a, b in coefs.items()}
    elif cand.cause == "random_walk":
        knot = cand.info["knot_s"]
        p["dps_per_sqrt_s"] = {a: _walk_intensity(prob, b, knot) for a, b in coefs.items()}
    return p


def _walk_intensity(prob: Problem, knots: np.ndarray, knot_s: float) -> float:
    """Random-walk intensity [deg/s/sqrt(s)] from the knot values' increments within sessions."""
    d, k = [], 0
    t_on, sess = prob.cols["t_on"], prob.usable.session
    for s in np.unique(sess):
        nk = int(np.ceil(t_on[sess == s].max() / knot_s)) + 1
        d.extend(np.diff(knots[k : k + nk]).tolist())
        k += nk
    return float(np.sqrt(np.mean(np.square(d)) / knot_s)) if d else 0.0
