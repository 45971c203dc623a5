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
- **A cold start that stops learning: the constant alone.** With no stored set, a unit whose data
  stops short of the structural rank was never calibrated: an autopilot's polynomial while the
  temperature stays put (an IMU held by its heater at 50 degC, a board warm before the daemon
  started: a PX4 at a steady 50 degC was rank 2 < 3 for as long as it ran), or seed 000's terms on a
  unit mounted at one pose in its vehicle (rank 1 < 9 for good). Once the session says the data has
  stopped adding directions (session.py, ``STEADY_S``) and the unit holds no set beyond a constant
  (``cold_ready``), the bias-only stage runs against a zero set: its constant term is the mean drift,
  every other term 0. That is right at the temperature and the pose seen, and no worse elsewhere than
  the bias it removes is; a full set follows when the data reaches the rank (a tumble, a warm-up).
- **A cold start that cannot separate its temperature terms: those held at 0.** One first-order
  warm-up makes dtemp a straight line in temp, so seed 000 + temp, temp^2, dtemp, temp*dtemp stops
  at rank 12 of 13 on a whole factory tumble. Once the session says the rank has stalled
  (session.py, ``HOLD_STALL_S``: ``may_hold``) and every gravity direction is determined, the terms
  the data cannot separate are held at 0 and the rest is an ordinary least-squares fit
  (model/held_zero.py): ``coefficients``, ``uncertainty``, ``prediction`` and the convergence rule's
  rank all read the restricted system. The next switch-on, warm-started, learns the held terms once
  its warm-up and the one carried in the record separate them.
- **Predicted drift.** What the user cares about is the drift a set leaves in the output, not the
  1-sigma of each coefficient. ``prediction`` gives the standard error of the set's prediction
  c^T phi, RMS over the poses seen and over the sphere, from the estimator's covariance:
  var_a(phi) = sigma_a^2 z^T R^+ z with z = M phi (docs/estimators.md). The session pushes when
  that is small against the drift the set removes, or below ``push.target_drift_dph``.
- **Temperature terms across switch-ons.** The bias is new at each switch-on; a unit's thermal
  curve is not. An acked set's record keeps the estimator's information on its temperature terms
  (terms made only of ``temp`` and ``dtemp``), with every other term (the constant, gravity, t_on)
  marginalised out: the Schur complement of R, b, q in the normalised terms (``temp_information``).
  The next switch-on adds it to its own statistics, so its fit is the least-squares fit of every
  warm-up seen, with a free bias for each (and gravity terms from this session, or held). A warm-up
  that covers 20-35 degC after one that covered 30-50 degC gives a set over 20-50 degC, not over
  20-35 (issue 10). The information adds up over switch-ons, with no decay (``estimator.forgetting``
  < 1 forgets it with the samples, as it forgets the samples). It is used only when the record's
  terms, normaliser and method (rls, batch) match this session's; else the session starts as before.
- **Thresholds in time, not samples.** The convergence windows default to seconds of still data at
  the unit's rate, and the per-coefficient bounds (``max_sigma_dps``, ``max_change_dps``) default
  to off: the predicted-drift gate replaces them, and it holds for a 0.002 deg/s fibre gyro and a
  0.5 deg/s MEMS part alike. A ``convergence`` section in the config still overrides each field.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache
from typing import Any

import numpy as np

from gyrocal.daemon.capabilities import learnt_set
from gyrocal.model.bias_kalman import load_bias_spec
from gyrocal.model.convergence import ConvergenceConfig
from gyrocal.model.held_zero import HeldZero, find_held
from gyrocal.model.identifiability import rank_aware_solve
from gyrocal.model.methods import make_estimator
from gyrocal.model.terms import TermSpec

TEMP_ATOMS = frozenset({"temp", "dtemp"})
"""Atoms of the terms whose information is carried across switch-ons (the unit's thermal curve)."""
INFO_METHODS = ("rls", "batch")
"""Estimators whose statistics are the least-squares information (R, b, q) the prior merges into."""


def temp_indices(names: list[str]) -> list[int]:
    """Indices of the terms made only of temperature atoms (``temp``, ``temp^2``, ``dtemp``...)."""
    spec = TermSpec.parse(names)
    return [i for i, t in enumerate(spec.terms) if t.atoms and t.atoms <= TEMP_ATOMS]


@lru_cache(maxsize=512)
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

    MIN_INFLATION_BLOCKS = 6
    WINDOW_S = 2.0
    """Seconds of still samples in the convergence windows (error ratio, change) and the minimum."""

    def __init__(self, cfg: Any, prior: Any | None = None, rate_hz: float = 1000.0) -> None:
        self._args = (cfg, prior, rate_hz)
        self.names = list(cfg.terms)
        est = cfg.estimator
        conv = dict(est["convergence"])
        # the stored set over this model's terms: the record's own, or the learnt set behind a
        # projected record (the unit held a subset; capabilities.learnt_set)
        prior_c = None if prior is None else learnt_set(prior, self.names)
        self.has_prior = prior_c is not None
        conv.setdefault("min_rank", 1 if self.has_prior else structural_rank(tuple(self.names)))
        n_win = max(200, int(self.WINDOW_S * rate_hz))
        conv.setdefault("window", n_win)
        conv.setdefault("min_samples", n_win)
        conv.setdefault("max_sigma_dps", float("inf"))  # the predicted-drift gate replaces these
        conv.setdefault("max_change_dps", float("inf"))
        conv_cfg = ConvergenceConfig.from_dict(conv, cfg.source, "estimator.convergence")
        kw: dict[str, Any] = {"forgetting": est["forgetting"], "convergence": conv_cfg}
        if prior_c is not None:
            kw["prior_dps"] = prior_c
        if est["method"] in ("lms", "nlms"):
            kw["mu" if est["method"] == "nlms" else "alpha"] = est["step"]
        if est["method"] == "kf":  # bias states with the intensities analyze wrote (model/bias_kalman.py)
            kw["bias"] = load_bias_spec(est["terms"], cfg.source)
        self.est = make_estimator(est["method"], self.names, **kw)
        self.full_rank = structural_rank(tuple(self.names))
        self.prior = prior_c
        self.const = self.names.index("1") if "1" in self.names else None
        # a cold start's bias-only stage, against a zero set, once the session sets cold_ready (the
        # module docstring)
        cold = prior_c is None and self.const is not None and len(self.names) > 1
        self._zero = np.zeros((3, len(self.names))) if cold else None
        self.cold_ready = False
        # a cold start whose rank stalled short of the structural rank with every gravity direction
        # determined holds at 0 the terms the data cannot separate, once the session sets may_hold
        # (held_zero.py, and the module docstring)
        self.may_hold = False
        # terms the stored set held at 0 (held_zero.py): still named while this session's set keeps them 0
        ident = getattr(prior, "identifiable", None) if self.has_prior else None
        self._prior_held = [n for n in (ident or {}).get("held_zero") or [] if n in self.names]
        # the session owes the unit its bias stage (the store could not record it): the stage stays
        # bias-only past full rank until it is pushed, as it would have been at the first still second
        self.owe_bias = False
        self._sum_res = np.zeros(3)  # sums of the stored set's residual [deg/s], for the bias
        self._sum_res2 = np.zeros(3)
        self._n = 0
        # the same residual's means over blocks of SCATTER_BLOCK_S of trained samples: their scatter is
        # the bias's error when the residual is not white (``_bias_sigma``)
        self._chunk = max(2, int(round(self.SCATTER_BLOCK_S * rate_hz)))
        self._part = np.zeros(3)  # the sum [deg/s] over the block being filled, and its samples
        self._part_n = 0
        self._n_blocks = 0  # blocks done, and the sums of their means and of their squares [deg/s]
        self._blk_sum = np.zeros(3)
        self._blk_sum2 = np.zeros(3)
        self.prior_left = self._prior_left(prior) if self.has_prior else {}
        # earlier warm-ups' information on the temperature terms (module docstring)
        self.prior_info: dict[str, Any] | None = None
        self.prior_range: tuple[float, float] | None = None  # [degC] of the information merged
        if self.has_prior:
            self.prior_info = self._merge_information(prior)
            stats = getattr(prior, "stats", None) or {}
            # the range of the information carried (a bias stage's own temp_range_c is its held set's)
            r = stats.get("temp_information_range_c", stats.get("temp_range_c"))
            if self.prior_info is not None and isinstance(r, list) and len(r) == 2:
                self.prior_range = (float(r[0]), float(r[1]))
        # reads of the estimator (eigen-decompositions of R) are pure functions of its state, which
        # only update_many changes: they are computed once per update and kept until the next one
        self._version = 0
        self._cache: dict[str, tuple[int, Any]] = {}

    def fresh(self) -> Learner:
        """A new learner from the same config and stored set: learning starts again (a session that
        has found north takes the Earth's rotation out of every sample from then on, earth_track.py)."""
        return Learner(*self._args)

    def _cached(self, key: str, compute: Any) -> Any:
        hit = self._cache.get(key)
        if hit is not None and hit[0] == self._version:
            return hit[1]
        value = compute()
        self._cache[key] = (self._version, value)
        return value

    @staticmethod
    def _prior_left(prior: Any) -> dict[str, np.ndarray]:
        """The stored set's own predicted drift left [deg/s] (3,), poses and sphere, if it recorded one."""
        pred = (getattr(prior, "stats", None) or {}).get("predicted_drift_dph") or {}
        out = {}
        for key in ("left_poses", "left_sphere"):
            v = pred.get(key) or {}
            if all(isinstance(v.get(a), int | float) for a in "xyz"):
                out[key] = np.array([v[a] for a in "xyz"], dtype=float) / 3600.0
        return out

    def _merge_information(self, prior: Any) -> dict[str, Any] | None:
        """Add the record's ``temp_information`` to the estimator; the dict merged, or None."""
        info = (getattr(prior, "stats", None) or {}).get("temp_information")
        if not isinstance(info, dict) or self.est.method not in INFO_METHODS:
            return None
        keep = temp_indices(self.names)
        norm = self.est.norm
        try:
            names_kept = [self.names[i] for i in keep]
            if not keep or info.get("terms") != self.names or info.get("keep") != names_kept:
                return None
            if not (np.allclose(info["norm_a"], norm.a[keep], rtol=1e-9, atol=0)
                    and np.isclose(info["y_scale"], norm.y_scale, rtol=1e-9)):
                return None
            k = len(keep)
            rk = np.asarray(info["R"], dtype=np.float64).reshape(k, k)
            bk = np.asarray(info["b"], dtype=np.float64).reshape(k, 3)
            qk = np.asarray(info["q"], dtype=np.float64).reshape(3)
            neff = float(info["neff"])
        except (KeyError, TypeError, ValueError):
            return None
        if not (np.all(np.isfinite(rk)) and np.all(np.isfinite(bk)) and np.all(np.isfinite(qk))
                and np.isfinite(neff) and neff > 0):
            return None
        p = len(self.names)
        R, b = np.zeros((p, p)), np.zeros((p, 3))
        R[np.ix_(keep, keep)] = rk
        b[keep] = bk
        self.est.add_information(R, b, np.maximum(qk, 0.0), neff)
        return info

    def temp_information(self) -> dict[str, Any] | None:
        """The estimator's information on the temperature terms, every other term marginalised out.

        For a record (module docstring): ``R`` (K, K), ``b`` (K, 3), ``q`` (3,) in normalised units,
        ``neff``, with the terms and normaliser they belong to. None when the model has no temperature
        term, or the method keeps no least-squares statistics.
        """
        keep = temp_indices(self.names)
        if not keep or self.est.method not in INFO_METHODS or self.est.samples == 0:
            return None
        R, b, q, neff = self.est._totals()
        other = [i for i in range(len(self.names)) if i not in keep]
        rkk, bk, qk = R[np.ix_(keep, keep)], b[keep], q.copy()
        if other:
            roo_inv = np.linalg.pinv(R[np.ix_(other, other)], rcond=1e-12, hermitian=True)
            rko = R[np.ix_(keep, other)]
            rkk = rkk - rko @ roo_inv @ rko.T
            bo = b[other]
            bk = bk - rko @ roo_inv @ bo
            qk = q - np.einsum("ia,ij,ja->a", bo, roo_inv, bo)
        rkk = (rkk + rkk.T) / 2.0
        norm = self.est.norm
        return {"terms": list(self.names), "keep": [self.names[i] for i in keep],
                "R": rkk.tolist(), "b": bk.tolist(), "q": np.maximum(qk, 0.0).tolist(), "neff": float(neff),
                "norm_a": norm.a[keep].tolist(), "y_scale": float(norm.y_scale), "method": self.est.method}

    def update_many(self, phi: np.ndarray, raw_dps: np.ndarray, t_s: np.ndarray | None = None) -> None:
        # only the Kalman filter uses time (its bias states move with dt); the others stay as they were
        self._version += 1
        self.est.update_many(phi, raw_dps, t_s if self.est.method == "kf" else None)
        base = self.prior if self.prior is not None else self._zero
        if base is not None:
            res = raw_dps - phi @ base.T
            ok = np.all(np.isfinite(res), axis=1)
            self._sum_res += res[ok].sum(axis=0)
            self._sum_res2 += (res[ok] ** 2).sum(axis=0)
            self._n += int(ok.sum())
            self._add_blocks(res[ok])

    def _add_blocks(self, res: np.ndarray) -> None:
        """Cut the residual (N, 3) [deg/s] into blocks of ``_chunk`` samples; keep their means' sums."""
        i = 0
        while i < len(res):
            j = min(len(res), i + self._chunk - self._part_n)
            self._part += res[i:j].sum(axis=0)
            self._part_n += j - i
            if self._part_n == self._chunk:
                m = self._part / self._chunk
                self._n_blocks += 1
                self._blk_sum += m
                self._blk_sum2 += m * m
                self._part, self._part_n = np.zeros(3), 0
            i = j

    SCATTER_BLOCK_S = 0.25
    MIN_SCATTER_BLOCKS = 4
    """Blocks of SCATTER_BLOCK_S [s] of residual the bias's error needs before their scatter may raise
    it above white noise's (a second of rest: a bias stage comes 1.6 s after a warm switch-on)."""

    def _bias_sigma(self) -> np.ndarray:
        """The bias stage's error (3,) [deg/s]: the standard error of the mean residual, white noise's
        (the per-sample variance over n), or, from MIN_SCATTER_BLOCKS blocks on, that of the block means
        when larger. Why: a warm-up's lag, or a slow turn taken for rest (one the still rule cannot see:
        model/still.py), puts a drift in a few blocks that white noise's error says nothing of; at a
        white error of 4.5 deg/h a bias stage moved y by 90.8 deg/h on such a turn and pushed it; one
        that moved an axis 4.22 deg/h on an error of 1.04 made it worse, 1.00 -> 3.22 deg/h (a fleet
        engineer's check)."""
        mean = self._sum_res / self._n
        var = np.maximum(self._sum_res2 / self._n - mean**2, 0.0)
        sig = np.sqrt(var / self._n)
        k = self._n_blocks
        if k >= self.MIN_SCATTER_BLOCKS:
            bm = self._blk_sum / k
            bvar = np.maximum(self._blk_sum2 / k - bm**2, 0.0) * k / (k - 1)
            sig = np.fmax(sig, np.sqrt(bvar / k))
        return sig

    @property
    def cold_bias(self) -> bool:
        """A cold start that may learn a constant-only set once its data stops adding directions
        (module docstring); the session decides when (``cold_ready``)."""
        return self._zero is not None

    @property
    def rank(self) -> int:
        """The number of directions this session's data has determined."""
        return int(self._identifiability().rank)

    @property
    def _base(self) -> np.ndarray | None:
        """The set the bias-only stage adds this switch-on's bias to: the stored one, or a zero set
        once a steady cold start may (``cold_ready``); None: no bias-only stage."""
        if self.prior is not None:
            return self.prior
        return self._zero if self.cold_ready else None

    @property
    def bias_only(self) -> bool:
        """True while a warm start lacks the excitation for a full update (see the module docstring)."""
        return (self._base is not None and self.const is not None and self._n > 0
                and (self.owe_bias or (self._identifiability().rank < self.full_rank
                                       and self.held_zero is None)))

    @property
    def held_zero(self) -> HeldZero | None:
        """The terms a stalled cold start holds at 0 (``may_hold``, held_zero.py), or None."""
        if not self.may_hold or self.prior is not None or self.est.method not in INFO_METHODS:
            return None
        return self._cached("held", self._find_held)

    def allow_hold(self) -> None:
        """The session's word that the rank has stalled (``may_hold``): reads are computed again."""
        self.may_hold = True
        self._version += 1

    def _find_held(self) -> HeldZero | None:
        ident = self._identifiability()
        if ident.rank >= self.full_rank or ident.rank == 0:
            return None
        return find_held(self.est._totals()[0], self.est.norm.M, self.names, ident.undetermined_terms,
                         structural_rank, self.est.rank_tol)

    def _identifiability(self) -> Any:
        return self._cached("ident", lambda: self.est.identifiability)

    @property
    def samples(self) -> int:
        return self.est.samples

    @property
    def coefficients(self) -> np.ndarray:
        base = self._base
        if self.bias_only and base is not None:
            c = base.copy()
            c[:, self.const] += self._sum_res / self._n
            return c
        held = self.held_zero
        if held is not None:
            c = self.est._physical(self._cached("solve", self._solve)[0])
            c[:, held.mask] = 0.0
            return c
        return self._cached("coefficients", lambda: self.est.coefficients).copy()

    @property
    def uncertainty(self) -> np.ndarray:
        if self.bias_only:
            sig = np.full((3, len(self.names)), np.inf)  # held at the stored values, not learnt here
            sig[:, self.const] = self._bias_sigma()
            return sig
        held = self.held_zero
        if held is not None:  # the kept terms' own 1-sigma; a term held at 0 is not determined
            _, var, lam_r, v_r, v_n = self._cached("solve", self._solve)
            m = self.est.norm.M
            g = m.T @ v_r
            sig = np.sqrt(var)[:, None] * np.sqrt((g * g / lam_r).sum(axis=1))[None, :]
            if v_n.size:
                sig[:, np.abs(m.T @ v_n).max(axis=1) > 1e-6 * max(1.0, np.abs(m).max())] = np.inf
            sig[:, held.mask] = np.inf
            return sig
        return self._cached("uncertainty", lambda: self.est.uncertainty).copy()

    def residual_var(self) -> np.ndarray:
        """Per-sample variance (3,) [deg/s^2] of the stored set's residual this session (bias stage)."""
        if self._n == 0:
            return np.zeros(3)
        mean = self._sum_res / self._n
        return np.maximum(self._sum_res2 / self._n - mean**2, 0.0)

    def identifiable(self) -> dict[str, Any]:
        out = self._identifiability().as_contract()
        held = self.held_zero
        if held is not None:
            out["held_zero"] = held.names(self.names)
        elif self._prior_held:  # a warm start keeps the stored set's held terms where its data is silent
            c = self.coefficients
            still_held = [n for n in self._prior_held if np.all(c[:, self.names.index(n)] == 0.0)]
            if still_held:
                out["held_zero"] = still_held
        return out

    @property
    def converged(self) -> tuple[bool, str]:
        st = self._cached("convergence", self._convergence)
        return st.converged, st.reason

    def _convergence(self) -> Any:
        """The estimator's convergence rule; with terms held at 0, the rank needed is what the kept
        terms can reach (the rank now, held_zero.py)."""
        est = self.est
        if self.held_zero is None:
            return est.convergence()
        conv = est.conv
        est.conv = replace(conv, min_rank=min(conv.min_rank, self.rank))
        try:
            return est.convergence()
        finally:
            est.conv = conv

    def state(self) -> dict[str, Any]:
        return self.est.state()

    def prediction(self, poses_phi: np.ndarray, sphere_phi: np.ndarray,
                   applied_dps: np.ndarray | None, held_out: Any | None = None) -> dict[str, Any]:
        """Predicted drift [deg/s] (3,) the current set would leave, and the drift it would remove.

        ``left_poses`` / ``left_sphere``: RMS over the poses seen (K, P) / over the sphere (M, P) of
        the standard error of c^T phi (inf over the sphere while a direction it needs is not
        determined). ``removes``: RMS over the poses seen of (c - applied)^T phi, the drift in the
        present output that the set would take out. In the bias-only stage only the constant term
        is learnt: its standard error is the whole prediction error (the stored gravity terms are
        taken as they are).
        """
        c = self.coefficients
        applied = np.zeros_like(c) if applied_dps is None or np.shape(applied_dps) != c.shape \
            else np.asarray(applied_dps)
        removes = np.sqrt(np.mean((poses_phi @ (c - applied).T) ** 2, axis=0)) if len(poses_phi) \
            else np.full(3, np.nan)
        if self.bias_only:
            # the new bias's error plus the stored gravity terms' own (recorded when they were pushed)
            sig = self.uncertainty[:, self.const]
            zero = np.zeros(3)
            return {"left_poses": np.hypot(sig, self.prior_left.get("left_poses", zero)),
                    "left_sphere": np.hypot(sig, self.prior_left.get("left_sphere", zero)),
                    "removes": removes, "stage": "bias", "gate": sig}
        if self.est.samples == 0 or not len(poses_phi):
            inf = np.full(3, np.inf)
            return {"left_poses": inf, "left_sphere": inf.copy(), "removes": removes, "stage": "full"}
        est = self.est
        _, var, lam_r, v_r, v_n = self._cached("solve", self._solve)

        def rms_se(phi: np.ndarray, null_test: bool) -> np.ndarray:
            z = phi @ est.norm.M.T  # (K, P) normalised terms
            quad = (((z @ v_r) ** 2) / lam_r).sum(axis=1) if lam_r.size else np.full(len(z), np.inf)
            if null_test and v_n.size:  # a direction the data did not determine: prediction unknown
                size = np.maximum(np.linalg.norm(z, axis=1), 1e-300)
                quad = np.where(np.linalg.norm(z @ v_n, axis=1) > 1e-3 * size, np.inf, quad)
            return np.sqrt(var * np.mean(quad))

        # white noise is what sigma assumes; a real unit's noise is coloured (flicker, random walk) and
        # its model incomplete (temperature): the held-out blocks show by how much, through the scatter
        # of their residual means against what white noise would give (>= 1; 1 with too few blocks)
        infl = self._inflation(held_out, var, est, v_r, lam_r)
        return {"left_poses": rms_se(poses_phi, False) * infl, "left_sphere": rms_se(sphere_phi, True) * infl,
                "removes": removes, "stage": "full", "noise_inflation": infl}

    def wander_floor(self, over_s: float) -> np.ndarray | None:
        """The drift [deg/s] (3,) the bias's wander leaves over the next ``over_s`` seconds whatever set
        is pushed (refine.gate's floor), or None when the estimator has no wander model (every method
        but ``kf`` with a random walk or a bias instability in its spec) or is in its bias-only stage."""
        f = getattr(self.est, "wander_dps", None)
        if f is None or self.bias_only:
            return None
        floor = np.asarray(f(over_s), dtype=float)
        return floor if np.any(floor > 0) else None

    def _solve(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Normalised weights (P, 3), residual variance (3,) [deg/s^2] and the eigen-split of R they
        were solved with (with terms held at 0: of R restricted to the weights that keep them 0)."""
        est = self.est
        R, b, q, neff = est._totals()
        held = self.held_zero
        if held is None:
            w, lam_r, v_r, v_n = rank_aware_solve(R, b, est.w0, est.rank_tol)
        else:
            w, lam_r, v_r, v_n = held.solve(R, b, est.rank_tol)
        rss = np.maximum(q - 2 * (w * b).sum(axis=0) + (w * (R @ w)).sum(axis=0), 0.0)
        dof = neff - lam_r.size
        var = rss / dof if dof > 0 else np.full(3, np.inf)
        return w, var, lam_r, v_r, v_n

    def _inflation(self, blocks: Any, var: np.ndarray, est: Any, v_r: np.ndarray,
                   lam_r: np.ndarray) -> np.ndarray:
        """sqrt(observed / white-noise-expected) mean square of held-out block residuals, per axis."""
        if blocks is None or len(blocks) < self.MIN_INFLATION_BLOCKS or not lam_r.size:
            return np.ones(3)
        raw = np.array([b.raw_dps for b in blocks])
        phi = np.array([b.phi for b in blocks])
        n = np.array([b.n for b in blocks], dtype=float)
        res = raw - phi @ self.coefficients.T
        z = phi @ est.norm.M.T
        quad = (((z @ v_r) ** 2) / lam_r).sum(axis=1)
        expected = var[None, :] * (1.0 / n + quad)[:, None]
        ratio = np.mean(res**2, axis=0) / np.maximum(np.mean(expected, axis=0), 1e-300)
        return np.sqrt(np.maximum(ratio, 1.0))


def make_learner(cfg: Any, prior: Any | None, rate_hz: float = 1000.0) -> Learner:
    return Learner(cfg, prior, rate_hz)
