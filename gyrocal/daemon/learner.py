"""The daemon's view of an estimator: learn, report, and know when it may be pushed.

It wraps gyrocal.model's estimators with the two decisions that belong to the daemon:

- **Warm start.** A new switch-on starts from the unit's last acked calibration: the stored
  coefficients become the estimator's prior, held in every direction this session's data has not
  determined (the null space). A unit that sits in one orientation in its vehicle still gets its
  bias re-estimated at every switch-on, while the gravity terms it cannot see keep their stored
  values. That is seed 000's point: the bias changes from one switch-on to the next.
- **Rank needed.** With no stored calibration, nothing is pushed until the data determines every
  direction the model can determine at all (its structural rank: 9 of 10 for seed 000's terms,
  because gx^2 + gy^2 + gz^2 = 1). With a stored calibration, one determined direction suffices.
- **Bias-only update.** Until this session's data reaches the structural rank, a warm-started
  session changes only the constant term: the stored set plus this switch-on's bias, estimated as
  the mean residual of the stored set. A least-squares update would spread the bias change over
  every term that is 1 at the poses seen (1, gz, gz^2 at z up) and corrupt the others' stored
  values; the bias is the quantity that changes from one switch-on to the next.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from gyrocal.model.bias_kalman import load_bias_spec
from gyrocal.model.convergence import ConvergenceConfig
from gyrocal.model.methods import make_estimator
from gyrocal.model.terms import TermSpec


@lru_cache(maxsize=16)
def structural_rank(names: tuple[str, ...]) -> int:
    """The largest rank the terms can reach on a still unit: gravity on the unit sphere [g].

    Evaluated numerically on 400 random directions, with any non-gravity atom (temp, t_on, ...)
    drawn at random too, so an extended model's rank is found without special cases.
    """
    rng = np.random.default_rng(0)
    g = rng.normal(size=(400, 3))
    g /= np.linalg.norm(g, axis=1)[:, None]
    cols: dict[str, np.ndarray] = {"ax": g[:, 0], "ay": g[:, 1], "az": g[:, 2]}
    spec = TermSpec.parse(names)
    for atom in spec.atoms:
        base = atom.split("^")[0]
        if base not in ("gx", "gy", "gz", "ax", "ay", "az") and "(" not in base:
            cols[base] = rng.uniform(-1, 1, 400)
    cols.setdefault("t", rng.uniform(0, 100, 400))
    cols.setdefault("t_on", rng.uniform(0, 100, 400))
    return int(np.linalg.matrix_rank(spec.design(cols), tol=1e-8))


class Learner:
    """One session's estimator plus the daemon's push rules (see the module docstring)."""

    def __init__(self, cfg: Any, prior: Any | None = None) -> None:
        self.names = list(prior.terms) if prior is not None and list(prior.terms) == cfg.terms \
            else list(cfg.terms)
        est = cfg.estimator
        conv = dict(est["convergence"])
        self.has_prior = prior is not None and list(prior.terms) == self.names
        conv.setdefault("min_rank", 1 if self.has_prior else structural_rank(tuple(self.names)))
        kw: dict[str, Any] = {"forgetting": est["forgetting"],
                              "convergence": ConvergenceConfig.from_dict(conv, f"{cfg.source} estimator")}
        if self.has_prior:
            kw["prior_dps"] = np.asarray(prior.coefficients_dps, dtype=np.float64)
        if est["method"] in ("lms", "nlms"):
            kw["mu" if est["method"] == "nlms" else "alpha"] = est["step"]
        if est["method"] == "kf":  # bias states with the intensities analyze wrote (model/bias_kalman.py)
            kw["bias"] = load_bias_spec(est["terms"], cfg.source)
        self.est = make_estimator(est["method"], self.names, **kw)
        self.full_rank = structural_rank(tuple(self.names))
        self.prior = np.asarray(prior.coefficients_dps, dtype=np.float64) if self.has_prior else None
        self.const = self.names.index("1") if "1" in self.names else None
        self._sum_res = np.zeros(3)  # sums of the stored set's residual [deg/s], for the bias
        self._sum_res2 = np.zeros(3)
        self._n = 0

    def update_many(self, phi: np.ndarray, raw_dps: np.ndarray, t_s: np.ndarray | None = None) -> None:
        # only the Kalman filter uses time (its bias states move with dt); the others stay as they were
        self.est.update_many(phi, raw_dps, t_s if self.est.method == "kf" else None)
        if self.prior is not None:
            res = raw_dps - phi @ self.prior.T
            ok = np.all(np.isfinite(res), axis=1)
            self._sum_res += res[ok].sum(axis=0)
            self._sum_res2 += (res[ok] ** 2).sum(axis=0)
            self._n += int(ok.sum())

    @property
    def bias_only(self) -> bool:
        """True while a warm start lacks the excitation for a full update (see the module docstring)."""
        return (self.prior is not None and self.const is not None and self._n > 0
                and self.est.identifiability.rank < self.full_rank)

    @property
    def samples(self) -> int:
        return self.est.samples

    @property
    def coefficients(self) -> np.ndarray:
        if self.bias_only and self.prior is not None:
            c = self.prior.copy()
            c[:, self.const] += self._sum_res / self._n
            return c
        return self.est.coefficients

    @property
    def uncertainty(self) -> np.ndarray:
        if self.bias_only:
            sig = np.full((3, len(self.names)), np.inf)  # held at the stored values, not learnt here
            mean = self._sum_res / self._n
            var = np.maximum(self._sum_res2 / self._n - mean**2, 0.0)
            sig[:, self.const] = np.sqrt(var / self._n)
            return sig
        return self.est.uncertainty

    def identifiable(self) -> dict[str, Any]:
        return self.est.identifiability.as_contract()

    @property
    def converged(self) -> tuple[bool, str]:
        st = self.est.convergence()
        return st.converged, st.reason

    def state(self) -> dict[str, Any]:
        return self.est.state()


def make_learner(cfg: Any, prior: Any | None) -> Learner:
    return Learner(cfg, prior)
