"""The methods: seed 000's LMS (eqs. 5-7), NLMS, RLS with forgetting, batch least squares (eqs. 2-4),
and seed 003's Kalman filter with a bias state (bias_kalman.py).

Symbols (seed 000 section 2, filterpy style): z the normalised term vector f_n(x_i), W (P, 3) the
weights w_n, y the desired output, y_est = W^T z, e = y - y_est, alpha the learning factor.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gyrocal.errors import ConfigError
from gyrocal.model.bias_kalman import BiasKalman, BiasModel
from gyrocal.model.estimator import Estimator
from gyrocal.model.identifiability import rank_aware_solve, split_subspaces
from gyrocal.model.normalise import Normaliser
from gyrocal.model.terms import SEED000_TERMS, TermSpec

log = logging.getLogger("gyrocal.model")


@dataclass(frozen=True)
class SeedSchedule:
    """Seed 000 section 5: the learning factor falls from 0.95 to 0.4; epochs until the MSE is small.

    alpha falls linearly over the first ``decay_epochs`` epochs and then stays at ``alpha_end``.
    Training stops when the epoch MSE changes by less than ``rel_tol`` (relative) after the decay,
    or after ``max_epochs`` epochs, or when ``max_steps`` sample steps would be exceeded.
    """

    alpha_start: float = 0.95
    alpha_end: float = 0.4
    decay_epochs: int = 20
    max_epochs: int = 3000
    rel_tol: float = 1e-10
    max_steps: int = 2_000_000

    def alpha(self, epoch: int) -> float:
        f = min(epoch / max(self.decay_epochs - 1, 1), 1.0)
        return self.alpha_start + (self.alpha_end - self.alpha_start) * f


class LMS(Estimator):
    """Seed 000's functional-link LMS; on-line with a fixed ``alpha``, or ``train_seed`` (epochs).

    On line, W starts at the prior (zero) and each accepted sample applies eqs. (5)-(7). With
    ||z|| <= 1 (normalise.py) any 0 < alpha < 2 is stable. Weights that become non-finite or exceed
    ``w_max`` (normalised units) are reset, with a warning on the ``gyrocal.model`` logger.
    """

    method = "lms"

    def __init__(self, terms: Sequence[str] | TermSpec = SEED000_TERMS, *, alpha: float = 0.02, seed: int = 0,
                 w_max: float = 1e6, **kw: Any) -> None:
        super().__init__(terms, **kw)
        if not 0.0 < alpha < 2.0:
            raise ConfigError(
                f"LMS learning factor alpha={alpha!r} must be in (0, 2); the seed uses 0.95 -> 0.4")
        self.alpha, self.seed, self.w_max = float(alpha), int(seed), float(w_max)
        self.rng = np.random.default_rng(seed)

    def _config(self) -> dict[str, Any]:
        return {"alpha": self.alpha, "seed": self.seed, "w_max": self.w_max}

    def _step(self, z: np.ndarray, yn: np.ndarray) -> np.ndarray:
        e = yn - z @ self.W                                  # eqs. (5), (6): e = y - sum f_n w_n
        self.W += np.multiply.outer(self.alpha * z, e)       # eq. (7): w_n += alpha e f_n
        return e

    def _after_fold(self) -> None:
        self._check_divergence()

    def _check_divergence(self, random_init: bool = False) -> bool:
        big = np.abs(self.W).max() / self.norm.y_scale
        if np.isfinite(big) and big <= self.w_max:
            return False
        self.counts["resets"] += 1
        log.warning("%s: weights diverged (max |w| = %g) after %d samples; reset (%d resets so far)",
                    self.method, big, self.samples, self.counts["resets"])
        if random_init:
            self.W = self.rng.uniform(-1.0, 1.0, self.W.shape) * self.norm.y_scale
        else:
            self.W = self.w0.copy()
        return True

    def train_seed(self, phi: np.ndarray, y: np.ndarray, schedule: SeedSchedule | None = None) -> list[float]:
        """Seed 000 section 4-5: epochs over stored pairs phi (N, P), y (N, 3) [deg/s].

        W starts random in (-1, 1) (seeded), and each epoch presents every pair in order with eq. (7)
        at the epoch's alpha. Returns the MSE per epoch (normalised units). Only W changes: the
        statistics for uncertainty and identifiability come from ``absorb``. Pairs that are not
        finite or whose |y| exceeds the guard's ``max_rate_dps`` are left out, as ``absorb`` leaves them.
        """
        sch = schedule or SeedSchedule()
        # the pairs ``absorb`` refused are refused here too: a gyro of 1e300 deg/s, counted out_of_range
        # there, reached the epochs as an OverflowError (rc36b H6)
        with np.errstate(invalid="ignore"):
            keep = (np.isfinite(phi).all(axis=1) & np.isfinite(y).all(axis=1)
                    & (np.abs(y) <= self.guard.max_rate_dps).all(axis=1))
        z = np.asarray(phi, dtype=np.float64)[keep] * self._a - self._c
        yn = np.asarray(y, dtype=np.float64)[keep]
        self.W = self.rng.uniform(-1.0, 1.0, self.W.shape) * self.norm.y_scale  # (-1, 1) normalised
        epochs = max(min(sch.max_epochs, sch.max_steps // max(len(z), 1)),
                     min(sch.decay_epochs, sch.max_epochs))
        history: list[float] = []
        saved = self.alpha
        try:
            for epoch in range(epochs):
                self.alpha = sch.alpha(epoch)
                e = self._step_block(z, yn)
                mse = float(np.mean(e * e)) / self.norm.y_scale ** 2
                if self._check_divergence(random_init=True):
                    continue
                history.append(mse)
                if epoch >= sch.decay_epochs and len(history) > 1 and \
                        abs(history[-2] - mse) <= sch.rel_tol * max(mse, 1e-300):
                    break
        finally:
            self.alpha = saved
        return history

    def state(self) -> dict[str, Any]:
        d = super().state()
        d["rng"] = self.rng.bit_generator.state
        return d

    def _restore(self, d: dict[str, Any]) -> None:
        self.rng.bit_generator.state = d["rng"]


class NLMS(LMS):
    """Normalised LMS: W += mu e z / (eps + z^T z); stable for any input scale with 0 < mu < 2."""

    method = "nlms"

    def __init__(self, terms: Sequence[str] | TermSpec = SEED000_TERMS, *, mu: float = 0.02,
                 eps: float = 1e-6, **kw: Any) -> None:
        kw.pop("alpha", None)
        super().__init__(terms, alpha=mu, **kw)
        self.eps = float(eps)

    @property
    def mu(self) -> float:
        return self.alpha

    def _config(self) -> dict[str, Any]:
        return {"mu": self.alpha, "eps": self.eps, "seed": self.seed, "w_max": self.w_max}

    def _step(self, z: np.ndarray, yn: np.ndarray) -> np.ndarray:
        e = yn - z @ self.W                                              # a-priori error, eq. (6)
        self.W += np.multiply.outer(z, (self.alpha / (self.eps + np.dot(z, z))) * e)  # normalised eq. (7)
        return e


class RLS(Estimator):
    """Recursive least squares in information form, with forgetting factor lambda.

    R, b accumulate exactly (estimator.py); W = W0 + V_r diag(1/l_r) V_r^T (b - R W0) is solved
    rank-aware (identifiability.py) each time a block of ``block`` samples is folded in, and
    ``coefficients`` always solves on everything seen, so one pass gives the least-squares answer.
    The a-priori error of a sample uses W from the last fold (at most block - 1 samples old);
    ``block=1`` gives textbook per-sample RLS errors.
    """

    method = "rls"

    def _step(self, z: np.ndarray, yn: np.ndarray) -> np.ndarray:
        return yn - z @ self.W

    def _step_block(self, z: np.ndarray, yn: np.ndarray) -> np.ndarray:
        return yn - z @ self.W

    def _after_fold(self) -> None:
        self.W = rank_aware_solve(self.R, self.b, self.w0, self.rank_tol)[0]

    def _weights(self, R: np.ndarray, b: np.ndarray) -> np.ndarray:
        return rank_aware_solve(R, b, self.w0, self.rank_tol)[0]


class BatchLS(RLS):
    """Batch least squares, seed 000 eqs. (2)-(4): RLS without forgetting (lambda = 1)."""

    method = "batch"

    def __init__(self, terms: Sequence[str] | TermSpec = SEED000_TERMS, **kw: Any) -> None:
        if kw.get("forgetting", 1.0) != 1.0:
            raise ConfigError("batch least squares has no forgetting factor; use method 'rls' for one")
        super().__init__(terms, **kw)


def lstsq_reference(
    norm: Normaliser, phi: np.ndarray, y: np.ndarray, tol: float, w0: np.ndarray | None = None
) -> np.ndarray:
    """Eq. (4) by SVD of the normalised design, same rank rule (s_i^2 > tol s_max^2): coefficients (3, P)."""
    z = norm.z(np.asarray(phi, dtype=np.float64))
    yn = np.asarray(y, dtype=np.float64) / norm.y_scale
    w0 = np.zeros((z.shape[1], 3)) if w0 is None else w0
    u, s, vt = np.linalg.svd(z, full_matrices=False)
    keep = s**2 > tol * s[0] ** 2
    w = w0 + vt[keep].T @ ((u[:, keep].T @ (yn - z @ w0)) / s[keep, None])
    return norm.to_physical(w)


METHODS: dict[str, type[Estimator]] = {"lms": LMS, "nlms": NLMS, "rls": RLS, "batch": BatchLS,
                                       "kf": BiasKalman}


def make_estimator(method: str, terms: Sequence[str] | TermSpec = SEED000_TERMS, **kw: Any) -> Estimator:
    """The estimator for a method name (lms, nlms, rls, batch, kf); keyword args go to its constructor."""
    if method not in METHODS:
        raise ConfigError(f"unknown estimator method {method!r}; use one of {', '.join(METHODS)}")
    return METHODS[method](terms, **kw)


__all__ = ["LMS", "NLMS", "RLS", "BatchLS", "BiasKalman", "BiasModel", "SeedSchedule", "METHODS",
           "make_estimator", "lstsq_reference", "split_subspaces"]
