"""Generalised least squares under the state-space error model, by a banded solver (linear cost).

Why: the significance test weighs a candidate cause against the residual's own wander (flicker,
random walk), not against white noise. Under the error model of ``noisemodel`` the residual is
white noise plus latent slow states (each slow Gauss-Markov member, the walk), one value per sample.
Marginalising those states gives the residual covariance V; its inverse is applied through the
Woodbury identity

    V^-1 = I / s2 - A H^-1 A' / s2^2,   H = A'A / s2 + Omega

where A sums the latent states of a sample and Omega, the prior precision of the state chains, is
tridiagonal per chain. With the states of a sample interleaved, H is banded (bandwidth = number of
states), so one banded Cholesky factorisation (LAPACK pbtrf) costs O(M), where a dense design with
one walk knot per block cost O(M x knots) memory (10 GB on a 2.8-hour log).

Fast colour (correlation time of a few samples) enters as its low-frequency white level: against
slow regressors it acts as white noise of that variance. Time gaps (moves between still runs) are
honoured: the walk's variance grows and the Gauss-Markov correlation decays over the gap; each
session restarts the chains (the session offset regressor carries the level).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded, lapack

from gyrocal.analysis.noisemodel import NoiseModel

COLUMN_CHUNK = 8
"""Columns solved at once: bounds the memory to M x states x COLUMN_CHUNK floats."""
SEGMENT_ROWS = 1 << 18
"""Rows of the state system swept at once by ``gram`` (memory: SEGMENT_ROWS x P floats)."""
_tbtrs = getattr(lapack, "dtbtrs", None)
DT_FLOOR = 0.1
"""The shortest interval between samples the state model takes, in sample periods."""


class StateSpaceGLS:
    """V^-1 of one axis' error model on the used samples, optionally on training rows only.

    ``t`` [s] and ``session`` are per used sample, in time order within sessions. ``weight`` (M,)
    is 1 for rows that are observed and 0 for rows the model must predict (held-out rows).
    """

    def __init__(self, model: NoiseModel, t: np.ndarray, session: np.ndarray,
                 weight: np.ndarray | None = None) -> None:
        self.model = model
        self.s2 = model.lowfreq_white_var
        n = t.size
        self.n = n
        self.w = np.ones(n) if weight is None else np.asarray(weight, float)
        chains: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (phi_i, v_i) per sample
        dt = np.diff(t, prepend=t[0])
        start = np.concatenate(([True], session[1:] != session[:-1]))
        # a logger that repeats a time stamp (dt 0) would make a state's step variance 0 and its
        # precision infinite: the band matrix then is not positive definite (a traceback on a valid
        # log, found by an outside check). Such samples were taken about a period apart; a tenth of
        # one [s] keeps the states nearly tied and the factorisation sound.
        dt = np.where(start, 1.0 / model.rate_hz, np.maximum(dt, DT_FLOOR / model.rate_hz))
        for tau, var in model.slow:
            phi = np.exp(-dt / tau)
            v = var * (1 - phi**2)
            phi = np.where(start, 0.0, phi)
            v = np.where(start, var, v)
            chains.append((phi, np.maximum(v, 1e-30 * var)))
        if model.walk_q > 0:
            v = model.walk_q * dt
            chains.append((np.where(start, 0.0, 1.0), np.maximum(v, 1e-30)))
        self.d = d = len(chains)
        self.logdet_v = 0.0
        if d == 0:
            self.logdet_v = float(np.sum(self.w) * np.log(self.s2))
            return
        ab = np.zeros((d + 1, n * d))
        obs = self.w / self.s2
        for j, (phi, v) in enumerate(chains):
            prec = 1.0 / v
            diag = prec.copy()
            diag[:-1] += phi[1:] ** 2 * prec[1:]
            ab[d, j::d] = obs + diag
            off = -phi * prec  # coupling of sample i-1 and i (zero at a session start)
            ab[0, d + j::d] = off[1:]
            for j2 in range(j + 1, d):
                ab[d - (j2 - j), j2::d] = obs
        self.cb = cholesky_banded(ab, lower=False, overwrite_ab=True, check_finite=False)
        logdet_h = 2.0 * float(np.sum(np.log(self.cb[d])))
        logdet_omega = -float(sum(np.sum(np.log(v)) for _, v in chains))
        self.logdet_v = float(np.sum(self.w) * np.log(self.s2)) + logdet_h - logdet_omega

    def _latent(self, x: np.ndarray) -> np.ndarray:
        """H^-1 A' W x / s2, the posterior mean of the states given x (M, P): (M, d, P)."""
        p = x.shape[1]
        rhs = np.repeat((x * (self.w / self.s2)[:, None]), self.d, axis=0)
        z = cho_solve_banded((self.cb, False), rhs, check_finite=False)
        return z.reshape(self.n, self.d, p)

    def vinv(self, x: np.ndarray) -> np.ndarray:
        """V^-1 x on the observed rows (zero on the others), x (M, P) or (M,)."""
        one = x.ndim == 1
        x2 = x[:, None] if one else x
        out = x2 * (self.w / self.s2)[:, None]
        if self.d:
            for c in range(0, x2.shape[1], COLUMN_CHUNK):
                z = self._latent(x2[:, c : c + COLUMN_CHUNK])
                out[:, c : c + COLUMN_CHUNK] -= z.sum(axis=1) * (self.w / self.s2)[:, None]
        return out[:, 0] if one else out

    def smooth(self, r: np.ndarray) -> np.ndarray:
        """The slow states' sum at every row given the observed rows' residual r (M,) [deg/s]."""
        if not self.d:
            return np.zeros_like(r)
        return self._latent(r[:, None]).sum(axis=1)[:, 0]

    def gram(self, x: np.ndarray) -> np.ndarray:
        """x' V^-1 x (P, P) = x'Wx / s2 - |U'^-1 b|^2, b = A'Wx / s2, H = U'U.

        One banded triangular sweep (LAPACK tbtrs) instead of the two of a full solve, in row
        segments of ``SEGMENT_ROWS`` (the coupling of a segment to the previous one is the last
        ``d`` solved rows), so the memory stays M x states x ``COLUMN_CHUNK`` floats at most.
        """
        wx = x * (self.w / self.s2)[:, None]
        g = x.T @ wx
        if not self.d or _tbtrs is None:
            return g - (x.T @ (wx - self.vinv(x)) if self.d else 0.0)
        d, p = self.d, x.shape[1]
        rows = self.n * d
        seg = max(d, (SEGMENT_ROWS // d) * d)
        z_prev = np.zeros((0, p))
        for a in range(0, rows, seg):
            c = min(rows, a + seg)
            rhs = np.asfortranarray(np.repeat(wx[a // d : c // d], d, axis=0))
            if a:  # rows j < a + d depend on the previous segment's last d rows
                for j in range(a, min(a + d, c)):
                    for i in range(j - d, a):
                        rhs[j - a] -= self.cb[d + i - j, j] * z_prev[i - (a - d)]
            z, info = _tbtrs(self.cb[:, a:c], rhs, uplo="U", trans="T", overwrite_b=1)
            if info != 0:
                raise np.linalg.LinAlgError(f"tbtrs failed (info {info})")
            g -= z.T @ z
            z_prev = z[-d:]
        return g
