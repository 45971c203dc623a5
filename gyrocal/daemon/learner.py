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
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

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
        self.est = make_estimator(est["method"], self.names, **kw)

    def update_many(self, phi: np.ndarray, raw_dps: np.ndarray) -> None:
        self.est.update_many(phi, raw_dps)

    @property
    def samples(self) -> int:
        return self.est.samples

    @property
    def coefficients(self) -> np.ndarray:
        return self.est.coefficients

    @property
    def uncertainty(self) -> np.ndarray:
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
