"""The one estimator interface shared by LMS, NLMS, RLS and batch least squares.

All three gyro axes share one regressor: the functional-link term vector phi (P,) of seed 000
eq. (10), so the weights are W (P, 3) and one information matrix serves the three axes.

Every method keeps the same sufficient statistics, with z in normalised units (normalise.py) and
y in deg/s, and forgetting factor lambda (an exponential window; 1 = none):

    R_n = lambda R_(n-1) + z_n z_n^T      (P, P)   information matrix
    b_n = lambda b_(n-1) + z_n y_n^T      (P, 3)
    q_n = lambda q_(n-1) + y_n * y_n      (3,)     for the residual RMS and the uncertainty

They give the identifiability (identifiability.py), the 1-sigma uncertainty and the residual for
every method; the methods differ only in how the working weights W move per sample.

Accepted samples are staged in a block buffer of ``block`` rows and folded into (R, b, q) in one
vectorised step when it fills. ``update_many`` cuts its input at the same buffer boundaries and so
is the per-sample loop, only faster. Reads (``coefficients``, ``uncertainty``, ...) include the
staged rows without folding them, so reading never changes what comes next, and ``state()``
carries the staged rows, so a warm start continues exactly.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any, ClassVar

import numpy as np

from gyrocal.errors import ConfigError
from gyrocal.model.convergence import ConvergenceConfig, ConvergenceStatus
from gyrocal.model.identifiability import (
    DEFAULT_RANK_TOL,
    Identifiability,
    analyse,
    rank_aware_solve,
    split_subspaces,
)
from gyrocal.model.normalise import Normaliser
from gyrocal.model.terms import SEED000_TERMS, TermSpec

_NAN3 = np.full(3, np.nan)
_INF = math.inf


@dataclass(frozen=True)
class InputGuard:
    """Limits beyond which a sample is counted and skipped (never fed to the weights)."""

    max_rate_dps: float = 2000.0
    max_accel_g: float = 20.0


def _without_null(delta: np.ndarray, null: np.ndarray) -> np.ndarray:
    """Coefficient changes (3, P) with their part along the undetermined directions (K, P) removed."""
    if null.size == 0:
        return delta
    q, _ = np.linalg.qr(null.T)  # orthonormal basis of the null space, (P, K)
    return delta - (delta @ q) @ q.T


class Estimator:
    """Base of every method. Subclasses implement ``_step`` / ``_step_block`` (the W update).

    Args:
        terms: term names or a TermSpec (seed 000 eq. 10 by default), P terms.
        normaliser: the seed's input/output scaling; ``Normaliser.nominal(spec)`` by default.
        forgetting: lambda in (0, 1]; 1 keeps every sample (the batch least-squares solution).
        guard: input limits for bad-sample rejection.
        prior_dps: (3, P) coefficients held in the null space and used as the start [deg/s per unit].
        rank_tol: eigenvalues of R below rank_tol * max count as not excited.
        block: rows staged before R, b, q are updated (and RLS re-solves W).
        convergence: thresholds of the convergence rule.
    """

    method: ClassVar[str] = ""

    def __init__(
        self, terms: Sequence[str] | TermSpec = SEED000_TERMS, *, normaliser: Normaliser | None = None,
        forgetting: float = 1.0, guard: InputGuard | None = None, prior_dps: np.ndarray | None = None,
        rank_tol: float = DEFAULT_RANK_TOL, block: int = 256, convergence: ConvergenceConfig | None = None,
    ) -> None:
        self.spec = terms if isinstance(terms, TermSpec) else TermSpec.parse(terms)
        self.norm = normaliser or Normaliser.nominal(self.spec)
        if not 0.0 < forgetting <= 1.0:
            raise ConfigError(f"forgetting factor {forgetting!r} must be in (0, 1]; e.g. 0.9999")
        if block < 1:
            raise ConfigError(f"block {block!r} must be >= 1")
        p = len(self.spec)
        self.lam, self.guard = float(forgetting), guard or InputGuard()
        self.rank_tol, self.block = rank_tol, block
        self.conv = convergence or ConvergenceConfig()
        self.w0 = np.zeros((p, 3))
        if prior_dps is not None:
            self.w0 = self._internal(np.asarray(prior_dps, dtype=np.float64))
        self.W = self.w0.copy()
        self.R, self.b, self.q, self.neff = np.zeros((p, p)), np.zeros((p, 3)), np.zeros(3), 0.0
        self._Zb, self._Yb, self._Eb = np.empty((block, p)), np.empty((block, 3)), np.empty((block, 3))
        self._k = 0
        self.counts = {"accepted": 0, "nonfinite": 0, "out_of_range": 0, "time_backwards": 0, "resets": 0}
        self.last_t = -_INF
        self._err: deque[list[Any]] = deque()  # [n, sum e^2 (3,)] per folded block, for the window
        self._snaps: list[list[Any]] = []      # [n, coefficients (3,P)] at window boundaries (last two)
        self._a, self._c, self._max_rate = self.norm.a, self.norm.c, self.guard.max_rate_dps

    # W is kept in normalised input units and physical output units [deg/s]: y = W^T z, with
    # W = y_scale * W_normalised. LMS and NLMS are linear in y, so their trajectories are the seed's;
    # only the random start and the divergence limit use y_scale.
    def _physical(self, w: np.ndarray) -> np.ndarray:
        return (self.norm.M.T @ w).T

    def _internal(self, coeffs: np.ndarray) -> np.ndarray:
        return np.linalg.solve(self.norm.M.T, coeffs.T)

    def new_session(self) -> None:
        """Time may restart at a switch-on: forget the last accepted time (statistics are kept)."""
        self.last_t = -_INF

    # ---- the per-sample path -------------------------------------------------------------------
    def update(self, phi: np.ndarray, y: np.ndarray, t: float | None = None,
               accel_g: np.ndarray | None = None) -> np.ndarray:
        """One sample: phi (P,) ndarray of terms in their units, y (3,) gyro [deg/s], t [s], accel (3,) [g].

        Returns the a-priori error y - c^T phi (3,) [deg/s], or NaNs when the sample was skipped.
        """
        y0, y1, y2 = y.tolist() if type(y) is np.ndarray else y
        s = y0 + y1 + y2 + sum(phi.tolist()) + (0.0 if t is None else t)
        if not math.isfinite(s):
            self.counts["nonfinite"] += 1
            return _NAN3.copy()
        mr = self._max_rate
        if abs(y0) > mr or abs(y1) > mr or abs(y2) > mr or (
                accel_g is not None and not np.dot(accel_g, accel_g) <= self.guard.max_accel_g ** 2):
            self.counts["out_of_range"] += 1
            return _NAN3.copy()
        if t is not None:
            if t < self.last_t:
                self.counts["time_backwards"] += 1
                return _NAN3.copy()
            self.last_t = t
        z = phi * self._a - self._c
        e = self._step(z, y)
        k = self._k
        self._Zb[k], self._Yb[k], self._Eb[k] = z, y, e
        self.counts["accepted"] += 1
        self._k = k + 1
        if k + 1 == self.block:
            self._fold()
        return e

    def update_many(self, phi: np.ndarray, y: np.ndarray, t: np.ndarray | None = None,
                    accel_g: np.ndarray | None = None) -> np.ndarray:
        """A block, exactly as a loop of ``update``: phi (N, P), y (N, 3), t (N,), accel (N, 3).

        Returns the a-priori errors (N, 3) [deg/s], NaN rows where a sample was skipped.
        """
        good = self._screen(phi, y, t, accel_g)
        z = np.asarray(phi, dtype=np.float64)[good] * self._a - self._c
        yn = np.asarray(y, dtype=np.float64)[good]
        out = np.full((len(good), 3), np.nan)
        e = np.empty_like(yn)
        i, n = 0, len(z)
        while i < n:
            m = min(self.block - self._k, n - i)
            k = self._k
            e[i:i + m] = self._step_block(z[i:i + m], yn[i:i + m])
            self._Zb[k:k + m], self._Yb[k:k + m], self._Eb[k:k + m] = z[i:i + m], yn[i:i + m], e[i:i + m]
            self._k += m
            self.counts["accepted"] += m
            if self._k == self.block:
                self._fold()
            i += m
        out[good] = e
        return out

    def absorb(self, phi: np.ndarray, y: np.ndarray, t: np.ndarray | None = None) -> int:
        """Add samples to the statistics (R, b, q) only, not to W; returns how many were accepted.

        The fit path uses it when W comes from elsewhere (the seed's epoch training on still means).
        """
        good = self._screen(phi, y, t, None)
        self._fold()
        z = np.asarray(phi, dtype=np.float64)[good] * self._a - self._c
        yn = np.asarray(y, dtype=np.float64)[good]
        self.R, self.b, self.q, self.neff = self._folded(z, yn)
        self.counts["accepted"] += int(good.sum())
        return int(good.sum())

    def _screen(self, phi, y, t, accel_g) -> np.ndarray:
        """Vectorised ``update`` checks; counts the rejects and advances ``last_t``."""
        phi = np.atleast_2d(np.asarray(phi, dtype=np.float64))
        y = np.atleast_2d(np.asarray(y, dtype=np.float64))
        if phi.shape[1] != len(self.spec) or y.shape != (phi.shape[0], 3):
            raise ValueError(
                f"update_many wants phi (N, {len(self.spec)}) and y (N, 3), got {phi.shape}, {y.shape}")
        s = y.sum(axis=1) + phi.sum(axis=1) + (0.0 if t is None else np.asarray(t, dtype=np.float64))
        fin = np.isfinite(s)
        with np.errstate(invalid="ignore"):
            inr = fin & ~(np.abs(y) > self.guard.max_rate_dps).any(axis=1)
            if accel_g is not None:
                inr &= np.einsum("ij,ij->i", accel_g, accel_g) <= self.guard.max_accel_g ** 2
        good = inr
        if t is not None:
            tt = np.where(inr, t, -_INF)
            before = np.maximum.accumulate(np.concatenate(([self.last_t], tt)))
            back = inr & (np.asarray(t) < before[:-1])
            good = inr & ~back
            self.counts["time_backwards"] += int(back.sum())
            self.last_t = float(before[-1])
        self.counts["nonfinite"] += int((~fin).sum())
        self.counts["out_of_range"] += int((fin & ~inr).sum())
        return good

    # ---- what a method supplies ------------------------------------------------------------------
    def _step(self, z: np.ndarray, yn: np.ndarray) -> np.ndarray:
        """Update W with one sample z (P,) normalised, y (3,) [deg/s]; return the a-priori error (3,)."""
        raise NotImplementedError

    def _step_block(self, z: np.ndarray, yn: np.ndarray) -> np.ndarray:
        """As ``_step`` over rows that fit in the current block; default: the loop."""
        e = np.empty_like(yn)
        for i in range(len(z)):
            e[i] = self._step(z[i], yn[i])
        return e

    def _after_fold(self) -> None:
        """Hook after the statistics absorbed a block (RLS re-solves W, LMS checks divergence)."""

    def _weights(self, R: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The reported normalised weights (P, 3): W with its null-space part held at the prior."""
        _, _, v_n = split_subspaces(R, self.rank_tol)
        return self.W - v_n @ (v_n.T @ (self.W - self.w0))

    # ---- statistics ------------------------------------------------------------------------------
    def _folded(self, z: np.ndarray, yn: np.ndarray):
        """(R, b, q, neff) after folding rows z (m, P), yn (m, 3) into the current statistics."""
        m = len(z)
        if self.lam == 1.0:
            return self.R + z.T @ z, self.b + z.T @ yn, self.q + (yn * yn).sum(axis=0), self.neff + m
        wts = self.lam ** np.arange(m - 1, -1, -1.0)
        zw, f = z * wts[:, None], self.lam ** m
        return (f * self.R + zw.T @ z, f * self.b + zw.T @ yn, f * self.q + wts @ (yn * yn),
                f * self.neff + wts.sum())

    def _fold(self) -> None:
        k = self._k
        if k == 0:
            return
        self.R, self.b, self.q, self.neff = self._folded(self._Zb[:k], self._Yb[:k])
        self._err.append([k, (self._Eb[:k] ** 2).sum(axis=0)])
        while len(self._err) > 1 and sum(x[0] for x in self._err) - self._err[0][0] >= self.conv.window:
            self._err.popleft()
        self._k = 0
        self._after_fold()
        n = self.counts["accepted"]
        if not self._snaps or n - self._snaps[-1][0] >= self.conv.window:
            self._snaps = [*self._snaps[-1:], [n, self.coefficients]]

    def add_information(self, R: np.ndarray, b: np.ndarray, q: np.ndarray, neff: float) -> None:
        """Add earlier data's statistics (normalised units, this estimator's normaliser) as a prior.

        R (P, P), b (P, 3), q (3,), neff: what those samples would have added to R, b, q, n_eff. The
        sample counts (``samples``, convergence windows) are not changed: they stay this session's.
        """
        self._fold()
        self.R = self.R + np.asarray(R, dtype=np.float64)
        self.b = self.b + np.asarray(b, dtype=np.float64)
        self.q = self.q + np.asarray(q, dtype=np.float64)
        self.neff += float(neff)
        self._after_fold()

    def _totals(self):
        if self._k:
            return self._folded(self._Zb[:self._k], self._Yb[:self._k])
        return self.R, self.b, self.q, self.neff

    # ---- reads -----------------------------------------------------------------------------------
    @property
    def samples(self) -> int:
        return self.counts["accepted"]

    @property
    def coefficients(self) -> np.ndarray:
        """Coefficients (3, P) [deg/s per term unit], physical units whatever the normalisation."""
        R, b, _, _ = self._totals()
        return self._physical(self._weights(R, b))

    @property
    def identifiability(self) -> Identifiability:
        return analyse(self._totals()[0], self.spec.names, self.norm.M, self.rank_tol)

    @property
    def uncertainty(self) -> np.ndarray:
        """1-sigma (3, P) [deg/s per term unit] of the least-squares estimate; +inf if undetermined.

        sigma_a^2 = RSS_a / (n_eff - rank), Cov(c_a) = sigma_a^2 M^T R^+ M. For LMS / NLMS it is a
        lower bound (their gradient noise adds to it).
        """
        R, b, q, neff = self._totals()
        w, lam_r, v_r, v_n = rank_aware_solve(R, b, self.w0, self.rank_tol)
        rss = np.maximum(q - 2 * (w * b).sum(axis=0) + (w * (R @ w)).sum(axis=0), 0.0)
        dof = neff - lam_r.size
        var = rss / dof if dof > 0 else np.full(3, np.inf)
        m = self.norm.M
        g = m.T @ v_r                          # (P, r)
        base = np.sqrt((g * g / lam_r).sum(axis=1)) if lam_r.size else np.full(len(m), np.inf)
        touched = np.zeros(len(m), dtype=bool)
        if v_n.size:
            touched = np.abs(m.T @ v_n).max(axis=1) > 1e-6 * max(1.0, np.abs(m).max())
        sig = np.sqrt(var)[:, None] * base[None, :]
        sig[:, touched] = np.inf
        return sig

    @property
    def residual_rms_dps(self) -> np.ndarray:
        """RMS (3,) [deg/s] of y - c^T phi over the (forgetting-weighted) samples, for the reported c."""
        R, b, q, neff = self._totals()
        w = self._weights(R, b)
        rss = np.maximum(q - 2 * (w * b).sum(axis=0) + (w * (R @ w)).sum(axis=0), 0.0)
        return np.sqrt(rss / max(neff, 1e-300))

    def convergence(self) -> ConvergenceStatus:
        """The convergence rule of convergence.py: ``converged`` and the first reason it is not."""
        cfg, n = self.conv, self.samples
        err = list(self._err) + ([[self._k, (self._Eb[:self._k] ** 2).sum(axis=0)]] if self._k else [])
        n_err = sum(x[0] for x in err)
        e_rms = np.sqrt(sum(x[1] for x in err) / max(n_err, 1)) if err else np.full(3, np.inf)
        resid = self.residual_rms_dps
        ratio = float(np.max(e_rms / np.maximum(resid, 1e-12)))
        ident = self.identifiability
        rank = ident.rank
        sig = self.uncertainty
        det = np.isfinite(sig[0])
        if det.any():
            max_sig = float(sig[:, det].max())
        else:
            # no coefficient is determined on its own (e.g. one pose, with a prior holding the rest):
            # judge the combinations the data did determine, through the fitted output's 1-sigma
            max_sig = float(np.max(resid / np.sqrt(max(n, 1)))) if rank else _INF
        change = _INF
        if len(self._snaps) == 2:
            delta = self._snaps[1][1] - self._snaps[0][1]
            if det.any():
                change = float(np.abs(delta)[:, det].max())
            elif rank:
                change = float(np.abs(_without_null(delta, ident.null_physical)).max())
        metrics = {"samples": n, "rank": rank, "error_ratio": ratio, "change_dps": change,
                   "max_sigma_dps": max_sig}
        checks = [
            (n >= cfg.min_samples, f"only {n} of {cfg.min_samples} samples"),
            (rank >= cfg.min_rank,
             f"rank {rank} < {cfg.min_rank}: the data has not excited enough directions yet "
             "(orientations, or temperatures for temperature terms)"),
            (ratio <= cfg.max_error_ratio,
             f"a-priori error {ratio:.2f}x the residual over the last {n_err} samples "
             f"(limit {cfg.max_error_ratio})"),
            (change <= cfg.max_change_dps,
             "coefficients not yet compared over a full window" if change == _INF else
             f"coefficients moved {change:.3g} deg/s over the last window (limit {cfg.max_change_dps:g})"),
            (max_sig <= cfg.max_sigma_dps,
             f"largest 1-sigma {max_sig:.3g} deg/s (limit {cfg.max_sigma_dps:g})"),
        ]
        for ok, why in checks:
            if not ok:
                return ConvergenceStatus(False, "not converged: " + why, metrics)
        return ConvergenceStatus(True, f"converged: error {ratio:.2f}x residual, change {change:.2g} deg/s, "
                                 f"1-sigma <= {max_sig:.2g} deg/s, rank {rank}", metrics)

    # ---- warm start ------------------------------------------------------------------------------
    def _config(self) -> dict[str, Any]:
        return {}

    def state(self) -> dict[str, Any]:
        """A JSON-serialisable snapshot; ``from_state`` continues exactly where this stopped."""
        k = self._k
        return {
            "method": self.method, "terms": self.spec.names, "normaliser": self.norm.state(),
            "forgetting": self.lam, "guard": asdict(self.guard), "rank_tol": self.rank_tol,
            "block": self.block, "convergence": asdict(self.conv), "config": self._config(),
            "w0": self.w0.tolist(), "W": self.W.tolist(), "R": self.R.tolist(), "b": self.b.tolist(),
            "q": self.q.tolist(), "neff": self.neff, "counts": dict(self.counts),
            "last_t": self.last_t if math.isfinite(self.last_t) else None,
            "staged": {"Z": self._Zb[:k].tolist(), "Y": self._Yb[:k].tolist(), "E": self._Eb[:k].tolist()},
            "err": [[n, s.tolist()] for n, s in self._err],
            "snaps": [[n, c.tolist()] for n, c in self._snaps],
        }

    @classmethod
    def from_state(cls, d: dict[str, Any]) -> Estimator:
        """Rebuild any method's estimator from ``state()`` output (dispatches on d['method'])."""
        from gyrocal.model.methods import METHODS
        klass = METHODS[d["method"]] if cls is Estimator else cls
        est = klass(d["terms"], normaliser=Normaliser.from_state(d["normaliser"]), forgetting=d["forgetting"],
                    guard=InputGuard(**d["guard"]), rank_tol=d["rank_tol"], block=d["block"],
                    convergence=ConvergenceConfig(**d["convergence"]), **d["config"])
        arr = np.asarray
        est.w0, est.W, est.R, est.b, est.q = (arr(d[k], dtype=np.float64).reshape(getattr(est, k).shape)
                                              for k in ("w0", "W", "R", "b", "q"))
        est.neff, est.counts = float(d["neff"]), dict(d["counts"])
        est.last_t = -_INF if d["last_t"] is None else float(d["last_t"])
        k = len(d["staged"]["Z"])
        for name, key in (("_Zb", "Z"), ("_Yb", "Y"), ("_Eb", "E")):
            if k:
                getattr(est, name)[:k] = arr(d["staged"][key], dtype=np.float64)
        est._k = k
        est._err = deque([n, arr(s, dtype=np.float64)] for n, s in d["err"])
        est._snaps = [[n, arr(c, dtype=np.float64)] for n, c in d["snaps"]]
        est._restore(d)
        return est

    def _restore(self, d: dict[str, Any]) -> None:
        """Hook for method-specific state (LMS's random generator)."""
