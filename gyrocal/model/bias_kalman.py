"""A Kalman filter with a bias state (seed 003's KF, method "kf"): the drift model plus a wandering bias.

Why: RLS with lambda = 1 learns the session's mean bias, so a bias random walk or flicker (issue 12)
is stale by the time the set is pushed, and forgetting ages the gravity terms with it. Here the
coefficients are constant states and the wander has its own states, with the intensities that
``gyrocal analyze`` found, so the filter knows how fast the bias may move and the gravity terms keep
their information.

Per axis a (the three axes share the regressor z but not the noise), seed 003 eqs. (7)-(9):

    state     x = [w (P,), b_rw, b_gm]        w: weights (normalised z, deg/s), b: bias parts [deg/s]
    model     x_k = F x_(k-1) + noise(Q),     F = diag(1..1, 1, exp(-dt/T)),
              Q = diag(0..0, q^2 dt, s^2 (1 - exp(-2 dt/T)))   (exact discretisation over dt [s])
    measure   gyro_k = H x_k + v,  H = [z^T, 1, 1],  v ~ N(0, R = sigma_white^2)

b_rw is present when a random-walk intensity q [deg/s/sqrt(s)] is given, b_gm when a Gauss-Markov
bias (stationary std s [deg/s], time constant T [s]) is: a bias instability B read at the Allan
floor tau_B is turned into s = 0.664 B / 0.6174, T = tau_B / 1.8926 (the Gauss-Markov Allan
deviation peaks at 0.6174 s, tau = 1.8926 T), the usual one-state stand-in for flicker.

R is the white noise per sample; when the spec does not give it, it is estimated on line by
covariance matching: E[r^2 + H P H^T] = R for the a-posteriori residual r (exact for a linear KF),
a running mean over the first ``noise_window`` samples, then a moving average over that many.

What the estimator reports: ``coefficients`` is what to push now, the weights with the tracked bias
added to the constant term (the "1" term; without one, see ``bias_state_dps``). A pushed set holds
for a while: the walk's best prediction is its current value, but the Gauss-Markov part decays to
zero with time constant T, so over a validity ``horizon_s`` H it is pushed at its mean,
b_gm T/H (1 - exp(-H/T)) (H = 0: its current value);
``uncertainty`` is the filter's posterior 1-sigma of that set (+inf along undetermined directions,
as for every method). The convergence rule's change test uses the coefficients without the tracked
bias (the wander is expected to move; the gravity terms should settle).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from gyrocal.errors import ConfigError
from gyrocal.model.allan import FLICKER_FLOOR
from gyrocal.model.estimator import Estimator
from gyrocal.model.terms import SEED000_TERMS, TermSpec

AXES = ("x", "y", "z")
GM_PEAK = 0.6174
"""Peak Allan deviation of a first-order Gauss-Markov rate per unit stationary std (at tau = 1.8926 T)."""
GM_PEAK_TAU = 1.8926


def _decay_mean(tau_s: np.ndarray, over_s: float) -> np.ndarray:
    """Mean over ``over_s`` [s] of exp(-t/tau) (a Gauss-Markov bias's decay): tau/H (1 - exp(-H/tau))."""
    return tau_s / over_s * (1.0 - np.exp(-over_s / tau_s))


def _zeros3() -> np.ndarray:
    return np.zeros(3)


@dataclass
class BiasModel:
    """Bias-state intensities per axis (x, y, z), the parts of the spec ``gyrocal analyze`` writes.

    random_walk_dps_per_sqrt_s: q [deg/s/sqrt(s)]; gm_sigma_dps: s [deg/s]; gm_tau_s: T [s];
    noise_dps: white noise per sample [deg/s], or None to estimate it on line.
    """

    random_walk_dps_per_sqrt_s: np.ndarray = field(default_factory=_zeros3)
    gm_sigma_dps: np.ndarray = field(default_factory=_zeros3)
    gm_tau_s: np.ndarray = field(default_factory=lambda: np.full(3, 100.0))
    noise_dps: np.ndarray | None = None

    @property
    def has_walk(self) -> bool:
        return bool(np.any(self.random_walk_dps_per_sqrt_s > 0))

    @property
    def has_gm(self) -> bool:
        return bool(np.any(self.gm_sigma_dps > 0))

    def as_dict(self) -> dict[str, Any]:
        return {"random_walk_dps_per_sqrt_s": self.random_walk_dps_per_sqrt_s.tolist(),
                "gm_sigma_dps": self.gm_sigma_dps.tolist(), "gm_tau_s": self.gm_tau_s.tolist(),
                "noise_dps": None if self.noise_dps is None else self.noise_dps.tolist()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> BiasModel:
        """Inverse of ``as_dict`` (the estimator's state and config)."""
        if not d:
            return cls()
        nd = d.get("noise_dps")
        return cls(np.asarray(d["random_walk_dps_per_sqrt_s"], dtype=np.float64),
                   np.asarray(d["gm_sigma_dps"], dtype=np.float64),
                   np.asarray(d["gm_tau_s"], dtype=np.float64),
                   None if nd is None else np.asarray(nd, dtype=np.float64))

    @classmethod
    def from_spec(cls, doc: Mapping[str, Any], source: str = "spec") -> BiasModel:
        """The intensities of an analysis spec (``gyrocal analyze LOG --json OUT.json`` writes
        OUT.terms.yaml).

        Keys read (each optional; per-axis values are {x:, y:, z:} mappings, a list of 3, or one number):

        - ``random_walk: {dps_per_sqrt_s: {x: q, ...}}`` (or ``causes.random_walk.params``);
        - ``gauss_markov: {sigma_dps: ..., tau_s: ...}``: a Gauss-Markov bias;
        - ``bias_instability: {dps: B, tau_s: tau_B}``: the Allan floor B/0.664 at tau_B [s],
          turned into a Gauss-Markov bias (module docstring);
        - ``noise_dps``: the white noise per sample [deg/s].
        """
        if not isinstance(doc, Mapping):
            raise ConfigError(f"{source}: a bias spec must be a mapping (random_walk:, noise_dps:, ...)")
        m = cls()
        rw = doc.get("random_walk")
        if rw is None:
            rw = ((doc.get("causes") or {}).get("random_walk") or {}).get("params")
        if rw is not None:
            q = rw.get("dps_per_sqrt_s", rw) if isinstance(rw, Mapping) else rw
            m.random_walk_dps_per_sqrt_s = _axes(q, source, "random_walk.dps_per_sqrt_s")
        gm = doc.get("gauss_markov")
        if gm is not None:
            if not isinstance(gm, Mapping) or "sigma_dps" not in gm or "tau_s" not in gm:
                raise ConfigError(f"{source}: field 'gauss_markov' needs sigma_dps and tau_s "
                                  "(e.g. {sigma_dps: {x: 0.001, y: 0.001, z: 0.001}, tau_s: 200})")
            m.gm_sigma_dps = _axes(gm["sigma_dps"], source, "gauss_markov.sigma_dps")
            m.gm_tau_s = _axes(gm["tau_s"], source, "gauss_markov.tau_s", positive=True)
        bi = doc.get("bias_instability")
        if bi is not None:
            if not isinstance(bi, Mapping) or "dps" not in bi or "tau_s" not in bi:
                raise ConfigError(f"{source}: field 'bias_instability' needs dps (B) and tau_s (where the "
                                  "Allan floor is), e.g. {dps: {x: 0.005, ...}, tau_s: 300}")
            b = _axes(bi["dps"], source, "bias_instability.dps")
            m.gm_sigma_dps = FLICKER_FLOOR * b / GM_PEAK
            m.gm_tau_s = _axes(bi["tau_s"], source, "bias_instability.tau_s", positive=True) / GM_PEAK_TAU
        if doc.get("noise_dps") is not None:
            m.noise_dps = _axes(doc["noise_dps"], source, "noise_dps", positive=True)
        return m


def load_bias_spec(terms: Any, config_path: str | Path) -> BiasModel:
    """The bias intensities for a daemon config's ``estimator.terms``: read from the terms file.

    ``gyrocal analyze LOG --json OUT.json`` writes OUT.terms.yaml with ``terms`` and the bias blocks,
    so naming that file as the estimator's terms brings both. ``seed000`` or an inline list: no bias states
    (the filter is then a Kalman form of RLS). A relative path is taken from the config's directory.
    """
    if not isinstance(terms, str) or terms == "seed000":
        return BiasModel()
    path = Path(terms)
    if not path.is_absolute():
        path = Path(config_path).parent / path
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{path}: cannot read the bias spec ({err}); name the terms file "
                          "`gyrocal analyze` wrote") from None
    return BiasModel.from_spec(doc if isinstance(doc, Mapping) else {}, str(path))


def _axes(v: Any, source: str, name: str, positive: bool = False) -> np.ndarray:
    try:
        if isinstance(v, Mapping):
            out = np.array([float(v.get(a, 0.0)) for a in AXES])
        else:
            out = np.broadcast_to(np.asarray(v, dtype=np.float64), (3,)).copy()
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: field '{name}' must be a number or {{x: , y: , z: }} numbers") from None
    if not np.all(np.isfinite(out)) or np.any(out < 0) or (positive and np.any(out <= 0)):
        raise ConfigError(f"{source}: field '{name}' must hold finite numbers "
                          f"{'> 0' if positive else '>= 0'}, got {out.tolist()}")
    return out


class BiasKalman(Estimator):
    """Kalman filter over the drift weights and a wandering bias (module docstring).

    Args (beyond the Estimator's):
        bias: the intensities (``BiasModel.from_spec``); all zero makes it a Kalman form of RLS.
        dt_s: sample interval [s] used when no time stamps are given.
        prior_sigma_dps: prior 1-sigma of every weight [deg/s per unit z]. The data decides whatever it
            is (the prior weighs like R / prior^2 samples, ~1e-5 of one sample), but the larger it is
            the worse P is conditioned; 1 deg/s covers tactical and consumer MEMS drift.
        noise0_dps: start of the on-line white-noise estimate when bias.noise_dps is None [deg/s].
        noise_window: samples over which the white-noise estimate averages.
        horizon_s: how long a pushed set is expected to hold [s]; weighs the Gauss-Markov bias.
    """

    method = "kf"

    def __init__(self, terms: Sequence[str] | TermSpec = SEED000_TERMS, *,
                 bias: BiasModel | Mapping | None = None, dt_s: float = 0.01, prior_sigma_dps: float = 1.0,
                 noise0_dps: float = 0.01, noise_window: int = 2000, horizon_s: float = 0.0,
                 **kw: Any) -> None:
        super().__init__(terms, **kw)
        if isinstance(bias, Mapping):
            bias = BiasModel.from_dict(bias)
        self.bias = bias or BiasModel()
        if not dt_s > 0 or not prior_sigma_dps > 0 or not noise0_dps > 0 or noise_window < 1 \
                or not horizon_s >= 0:
            raise ConfigError("kf: dt_s, prior_sigma_dps and noise0_dps must be > 0, noise_window >= 1 "
                              "and horizon_s >= 0")
        self.horizon_s = float(horizon_s)
        self.dt_s, self.prior_sigma, self.noise0 = float(dt_s), float(prior_sigma_dps), float(noise0_dps)
        self.noise_window = int(noise_window)
        p = len(self.spec)
        self.i_rw = p if self.bias.has_walk else None
        self.i_gm = p + int(self.bias.has_walk) if self.bias.has_gm else None
        n = p + int(self.bias.has_walk) + int(self.bias.has_gm)
        self.n_state = n
        # X (n, 3): one column per axis; W (the base class's weights) is a view of its first P rows
        self.X = np.zeros((n, 3))
        self.X[:p] = self.w0
        self.W = self.X[:p]
        self.P = np.zeros((3, n, n))                      # posterior covariance per axis
        self.P[:, np.arange(p), np.arange(p)] = self.prior_sigma ** 2
        self.Rv = (self.bias.noise_dps ** 2 if self.bias.noise_dps is not None
                   else np.full(3, self.noise0 ** 2))    # R per axis [(deg/s)^2]
        self.kf_t: float | None = None                    # time of the last filtered sample [s]
        self.kf_n = 0                                     # samples in the white-noise estimate
        self._h = np.zeros(n)
        self._h[p:] = 1.0
        self._tq: np.ndarray | None = None
        self._tq_i = 0
        self._t_one: float | None = None

    # ---- time stamps for dt --------------------------------------------------------------------
    def update(self, phi, y, t=None, accel_g=None):
        self._t_one, self._tq = (None if t is None else float(t)), None
        return super().update(phi, y, t, accel_g)

    def _screen(self, phi, y, t, accel_g) -> np.ndarray:
        good = super()._screen(phi, y, t, accel_g)
        self._tq = None if t is None else np.asarray(t, dtype=np.float64)[good]
        self._tq_i, self._t_one = 0, None
        return good

    def new_session(self) -> None:
        super().new_session()
        self.kf_t = None

    def _dt(self, t: float | None) -> float:
        if t is None or self.kf_t is None:
            dt = self.dt_s
        else:
            dt = max(t - self.kf_t, 0.0)
        if t is not None:
            self.kf_t = t
        return dt

    # ---- the filter ------------------------------------------------------------------------------
    def _step(self, z: np.ndarray, yn: np.ndarray) -> np.ndarray:
        return self._kf(z, yn, self._dt(self._t_one))

    def _step_block(self, z: np.ndarray, yn: np.ndarray) -> np.ndarray:
        e = np.empty_like(yn)
        tq, i0 = self._tq, self._tq_i
        for i in range(len(z)):
            e[i] = self._kf(z[i], yn[i], self._dt(None if tq is None else float(tq[i0 + i])))
        self._tq_i = i0 + len(z)
        return e

    def _kf(self, z: np.ndarray, meas: np.ndarray, dt: float) -> np.ndarray:
        """One predict + update for the three axes; meas (3,) is the gyro [deg/s] (filterpy's z)."""
        bm, X, P, h = self.bias, self.X, self.P, self._h
        p = len(z)
        h[:p] = z                                              # H = [z^T, 1, 1]
        # predict: x = F x ;  P = F P F^T + Q   (F is diagonal: 1, and exp(-dt/T) for b_gm)
        if self.i_rw is not None:
            P[:, self.i_rw, self.i_rw] += bm.random_walk_dps_per_sqrt_s ** 2 * dt
        if self.i_gm is not None:
            g = self.i_gm
            f = np.exp(-dt / bm.gm_tau_s)                      # (3,)
            X[g] *= f
            P[:, g, :] *= f[:, None]
            P[:, :, g] *= f[:, None]
            P[:, g, g] += bm.gm_sigma_dps ** 2 * (1.0 - f * f)
        # y = meas - H x   (innovation, the a-priori error)
        y = meas - h @ X
        # S = H P H^T + R
        PHt = P @ h                                            # (3, n)
        S = PHt @ h + self.Rv
        # K = P H^T S^-1
        K = PHt / S[:, None]
        # x = x + K y
        X += (K * y[:, None]).T
        # P = (I - K H) P (I - K H)^T + K R K^T   (Joseph form: stays symmetric positive definite)
        A = -K[:, :, None] * h[None, None, :]
        A[:, np.arange(self.n_state), np.arange(self.n_state)] += 1.0
        P[:] = A @ P @ A.transpose(0, 2, 1) + self.Rv[:, None, None] * (K[:, :, None] * K[:, None, :])
        if self.bias.noise_dps is None:
            # R = E[r^2 + H P H^T] with r = meas - H x the a-posteriori residual (covariance matching)
            r = meas - h @ X
            self.kf_n += 1
            beta = 1.0 / min(self.kf_n, self.noise_window)      # running mean, then a moving window
            self.Rv = (1.0 - beta) * self.Rv + beta * (r * r + (P @ h) @ h)
        return y

    # ---- reads -----------------------------------------------------------------------------------
    def _bias_weights(self) -> np.ndarray:
        """Weight of each bias state in the pushed constant (n - P, 3): 1 for b_rw, horizon mean for b_gm."""
        w = np.ones((self.n_state - len(self.spec), 3))
        if self.i_gm is not None and self.horizon_s > 0:
            w[-1] = _decay_mean(self.bias.gm_tau_s, self.horizon_s)
        return w

    @property
    def bias_state_dps(self) -> np.ndarray:
        """The tracked bias to push, b_rw + b_gm (its mean over ``horizon_s``), (3,) [deg/s]."""
        return (self.X[len(self.spec):] * self._bias_weights()).sum(axis=0)

    def wander_dps(self, over_s: float) -> np.ndarray:
        """RMS over the next ``over_s`` seconds of the bias's move away from what is pushed now, (3,)
        [deg/s]: the drift the wander leaves whatever set is pushed (the push gate's floor).

        The walk leaves q^2 H / 2 in mean square over H = ``over_s`` (its value now is its best
        prediction). The Gauss-Markov part pushed at w_p b0 (``_bias_weights``; w_p = 1 with no
        ``horizon_s``) leaves s^2 (1 + w_p^2 - 2 w_p w_H), w_H = T/H (1 - exp(-H/T)) the mean of its
        decay over H. The estimator's own error in the bias is not in it (that is the predicted drift).
        """
        h = max(float(over_s), 1e-9)
        ms = self.bias.random_walk_dps_per_sqrt_s ** 2 * h / 2.0
        if self.i_gm is not None:
            w_p = self._bias_weights()[-1]
            w_h = _decay_mean(self.bias.gm_tau_s, h)
            ms = ms + self.bias.gm_sigma_dps ** 2 * (1.0 + w_p**2 - 2.0 * w_p * w_h)
        return np.sqrt(ms)

    @property
    def noise_dps(self) -> np.ndarray:
        """The white noise per sample R^(1/2) in use, (3,) [deg/s]."""
        return np.sqrt(self.Rv)

    @property
    def static_coefficients(self) -> np.ndarray:
        """The weights as coefficients (3, P) [deg/s per term unit], without the tracked bias."""
        R, b, _, _ = self._totals()
        return self._physical(self._weights(R, b))

    def _const_index(self) -> int | None:
        return self.spec.names.index("1") if "1" in self.spec.names else None

    @property
    def coefficients(self) -> np.ndarray:
        """The set to push now (3, P): the weights plus the tracked bias in the constant term."""
        c = self.static_coefficients
        k = self._const_index()
        if k is not None:
            c[:, k] += self.bias_state_dps
        return c

    @property
    def uncertainty(self) -> np.ndarray:
        """Posterior 1-sigma (3, P) of ``coefficients`` from the filter's P; +inf where undetermined."""
        p = len(self.spec)
        G = np.zeros((p, self.n_state))
        G[:, :p] = self.norm.M.T
        G = np.broadcast_to(G, (3, p, self.n_state)).copy()
        k = self._const_index()
        if k is not None:
            G[:, k, p:] = self._bias_weights().T
        var = np.einsum("aij,ajk,aik->ai", G, self.P, G)
        sig = np.sqrt(np.maximum(var, 0.0))
        sig[np.isinf(super().uncertainty)] = np.inf
        return sig

    def _fold(self) -> None:
        last = self._snaps[-1] if self._snaps else None
        super()._fold()
        if self._snaps and self._snaps[-1] is not last:
            self._snaps[-1][1] = self.static_coefficients   # the change rule ignores the tracked bias

    # ---- warm start ------------------------------------------------------------------------------
    def _config(self) -> dict[str, Any]:
        return {"bias": self.bias.as_dict(), "dt_s": self.dt_s, "prior_sigma_dps": self.prior_sigma,
                "noise0_dps": self.noise0, "noise_window": self.noise_window, "horizon_s": self.horizon_s}

    def state(self) -> dict[str, Any]:
        d = super().state()
        d["kf"] = {"X": self.X.tolist(), "P": self.P.tolist(), "R": self.Rv.tolist(), "n": self.kf_n,
                   "t": self.kf_t if self.kf_t is not None and math.isfinite(self.kf_t) else None}
        return d

    def _restore(self, d: dict[str, Any]) -> None:
        kf = d["kf"]
        self.X[:] = np.asarray(kf["X"], dtype=np.float64)
        self.W = self.X[:len(self.spec)]
        self.P[:] = np.asarray(kf["P"], dtype=np.float64)
        self.Rv = np.asarray(kf["R"], dtype=np.float64)
        self.kf_t, self.kf_n = kf["t"], int(kf["n"])
