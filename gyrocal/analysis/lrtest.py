"""The significance test: a likelihood ratio under the fitted state-space error model.

Why not the old block t-test: it compared held-out blocks as if they were independent, so few
blocks, an effect concentrated in a few blocks, or real flicker (which inflates the spread between
blocks) each defeated it (issue 12). Here the residual's wander is part of the model: per axis the
error model of ``noisemodel`` (white + colour + flicker bank + walk) is fitted to the residual of
the largest model (baseline + every candidate, so a real effect does not inflate the noise), and
each candidate's columns are tested by generalised least squares under it:

    D = Q(model so far) - Q(model so far + candidate),   Q = min_beta (y - X beta)' V^-1 (y - X beta)

D is chi-square with the candidate's parameter count under the null when V is right. A nonlinear
choice made on the data pays a look-elsewhere factor (the number of independent frequencies
searched for a periodic cause, the warm-up grid). Each test costs one banded solve (linear in M).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from gyrocal.analysis.baseline import Problem, gram_solve, lstsq
from gyrocal.analysis.candidates import F_MIN_HZ, WARMUP_TAUS_S, Candidate
from gyrocal.analysis.gls import StateSpaceGLS
from gyrocal.analysis.noisemodel import NoiseModel, fit_noise

FGLS_ROUNDS = 1
UPPER_SIGMA = 2.0
"""The test's error model fits each Allan octave's upper 2-sigma limit (see ``fit_noise``)."""


def gls_fit(prob: Problem, model: NoiseModel, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """GLS coefficients of y (M,) on x (M, P) under an error model."""
    gls = StateSpaceGLS(model, prob.cols["t"], prob.usable.session)
    g = gls.gram(np.column_stack([x, y]))
    return gram_solve(g[:-1, :-1], g[:-1, -1], prob.n)


@dataclass
class AxisLR:
    """The likelihood-ratio test of one axis: columns per cause and error models per nested model."""

    prob: Problem
    axis: int
    cols: dict[str, np.ndarray]  # cause -> design columns (M, p)
    look_elsewhere: dict[str, float]
    models: dict[tuple[str, ...], NoiseModel] = field(default_factory=dict)  # ('point', ...) too
    warmup_tau_s: float | None = None  # this axis' warm-up tau when not the pooled one [s]
    tests: dict[tuple[tuple[str, ...], str], tuple[float, float]] = field(default_factory=dict)
    walks: dict[tuple[str, ...], WalkLR] = field(default_factory=dict)  # walk_lr's cache

    def design(self, causes: list[str] | tuple[str, ...]) -> np.ndarray:
        return np.column_stack([self.prob.base, *[self.cols[c] for c in causes]])

    def model_for(self, causes: list[str] | tuple[str, ...]) -> NoiseModel:
        """The error model of baseline + ``causes``, by feasible GLS (cached).

        Start from the model fitted on the baseline residual; estimate the coefficients by GLS under
        it (GLS leaves wander to the noise, where least squares would let a trend column soak up a
        slow flicker); refit the error model on that residual (``FGLS_ROUNDS`` = 1: two-step
        feasible GLS). A real effect is then removed before the noise is fitted (it is not taken for
        a walk), and a flicker is not removed by a column that only happens to look like it.

        Why one round, not more: where a column can stand in for the wander (a temperature that
        rises once per session against a 300 s flicker member), each further round lets the column
        take a little more of the wander, the refitted model then holds less slow power, and the next
        GLS leaves still more to the column. On flicker nulls two rounds took the walk to zero and
        named temperature (p = 1e-5) and temperature_rate (p = 4e-4) where the true error model gives
        p = 0.07 and 0.015 (seeds 30022, 30098); one round gives 0.02 and 0.01.
        """
        key = tuple(causes)
        if key not in self.models:
            y = self.prob.y[:, self.axis]
            if not key:
                beta, _ = lstsq(self.prob.base, y)
                self.models[key] = fit_noise(y - self.prob.base @ beta, self.prob.rate_hz, upper=UPPER_SIGMA)
            else:
                model = self.model_for(())
                x = self.design(key)
                for _ in range(FGLS_ROUNDS):
                    beta = gls_fit(self.prob, model, x, y)
                    model = fit_noise(y - x @ beta, self.prob.rate_hz, upper=UPPER_SIGMA)
                self.models[key] = model
        return self.models[key]

    @property
    def model(self) -> NoiseModel:
        return self.model_for(())

    def point_model_for(self, causes: list[str] | tuple[str, ...]) -> NoiseModel:
        """The error model of baseline + ``causes`` fitted to the octaves' point estimates (cached).

        The GLS coefficients are those under ``model_for`` (the upper-limit model); the noise is then
        refitted without ``upper``. This is the model the walk's smoother predicts held-out blocks
        with: an estimator should use the best estimate of the noise, and the upper limit, right for
        the null distribution of a regression test, gave the smoother slow power a white log does
        not have (random_walk named on quantised nulls 30028 and 30118 with it, not with this one).
        """
        key = ("point", *causes)
        if key not in self.models:
            x = self.design(list(causes))
            y = self.prob.y[:, self.axis]
            beta = gls_fit(self.prob, self.model_for(causes), x, y)
            self.models[key] = fit_noise(y - x @ beta, self.prob.rate_hz)
        return self.models[key]

    def test(self, chosen: list[str], cause: str) -> tuple[float, float]:
        """(D, p-value with the look-elsewhere factor) for adding ``cause`` to ``chosen``.

        The error model is the one fitted under the alternative (chosen + cause) by feasible GLS:
        an effect left in the residual would otherwise be taken for wander (a warm-up for a walk).
        Two-sided in the sense of a chi-square on the candidate's p columns.
        """
        key = (tuple(chosen), cause)
        if key in self.tests:
            return self.tests[key]
        model = self.model_for([*chosen, cause])
        gls = StateSpaceGLS(model, self.prob.cols["t"], self.prob.usable.session)
        y = self.prob.y[:, self.axis]
        g = gls.gram(np.column_stack([self.design([*chosen, cause]), y]))
        n0 = self.prob.base.shape[1] + sum(self.cols[c].shape[1] for c in chosen)
        d = _q(g, np.arange(n0), self.prob.n) - _q(g, np.arange(g.shape[0] - 1), self.prob.n)
        k = max(int(self.cols[cause].shape[1]), 1)
        p = float(min(1.0, self.look_elsewhere.get(cause, 1.0) * stats.chi2.sf(max(d, 0.0), k)))
        self.tests[key] = (float(d), p)
        return self.tests[key]

    def test_joint(self, chosen: list[str], causes: tuple[str, ...]) -> tuple[float, float]:
        """(D, p-value) for adding several ``causes`` to ``chosen`` together (chi-square on all their
        columns, the look-elsewhere factors multiplied): covariates that stand in for each other
        (temperature and its rate) can fail one at a time and pass together."""
        key = (tuple(chosen), causes)
        if key in self.tests:
            return self.tests[key]
        model = self.model_for([*chosen, *causes])
        gls = StateSpaceGLS(model, self.prob.cols["t"], self.prob.usable.session)
        y = self.prob.y[:, self.axis]
        g = gls.gram(np.column_stack([self.design([*chosen, *causes]), y]))
        n0 = self.prob.base.shape[1] + sum(self.cols[c].shape[1] for c in chosen)
        d = _q(g, np.arange(n0), self.prob.n) - _q(g, np.arange(g.shape[0] - 1), self.prob.n)
        k = max(sum(int(self.cols[c].shape[1]) for c in causes), 1)
        look = float(np.prod([self.look_elsewhere.get(c, 1.0) for c in causes]))
        p = float(min(1.0, look * stats.chi2.sf(max(d, 0.0), k)))
        self.tests[key] = (float(d), p)
        return self.tests[key]


def _q(gram: np.ndarray, idx: np.ndarray, n: int) -> float:
    """GLS residual quadratic form of y on the columns idx (y is the Gram's last column)."""
    iy = gram.shape[0] - 1
    g = gram[np.ix_(idx, idx)]
    b = gram[idx, iy]
    beta = gram_solve(g, b, n)
    return float(gram[iy, iy] - b @ beta)


def search_factor(prob: Problem, cause: str) -> float:
    """How many independent choices a nonlinear search made (look-elsewhere factor)."""
    if cause == "periodic":
        span = 0.0
        for s in np.unique(prob.usable.session):
            t = prob.cols["t"][prob.usable.session == s]
            span += float(t.max() - t.min())
        return max(1.0, (0.45 * prob.rate_hz - F_MIN_HZ) * span)
    if cause == "warmup":
        return float(len(WARMUP_TAUS_S))
    return 1.0


def build_axis_lr(prob: Problem, cands: list[Candidate], axis: int) -> AxisLR:
    """The test of one axis over the regression candidates (the walk is a state, not a column).

    The warm-up's column is this axis' own (``axis_warmup``): the candidate's time constant is
    chosen by least squares pooled over the axes, which a wandering neighbour axis pulls away from
    the true one.
    """
    regs = [c for c in cands if c.cause != "random_walk" and c.full.shape[1]]
    lr = AxisLR(prob, axis, {c.cause: c.full for c in regs},
                {c.cause: search_factor(prob, c.cause) for c in regs})
    if "warmup" in lr.cols:
        lr.cols["warmup"], lr.warmup_tau_s = axis_warmup(lr, lr.cols["warmup"])
        lr.look_elsewhere["warmup"] = float(len(WARMUP_TAUS_S) + 1)
    return lr


def axis_warmup(lr: AxisLR, pooled: np.ndarray) -> tuple[np.ndarray, float | None]:
    """The warm-up column exp(-t_on / tau) (M, 1) of one axis and its tau [s] (None = the pooled one).

    tau is the grid point (``WARMUP_TAUS_S``, cut at half the longest session, as the candidate's
    grid) or the candidate's pooled tau with the largest likelihood ratio D on this axis, under the
    axis' baseline error model. The test pays for that choice: its look-elsewhere factor is the
    grid's size + 1 (a Bonferroni bound over the choices; the taus are correlated, so it is
    conservative). Why (issue 12, injections into every shipped log): on tomisuarez tinit a 60 s
    warm-up injected on z at 0.25 sigma (oracle power 1.0) was missed: the pooled least-squares tau
    was 169 s, pulled by the slow wander of the other axes, and D at that tau was 6.1.
    """
    prob = lr.prob
    t_on = prob.cols["t_on"]
    t_max = float(np.max(t_on))
    taus = [t for t in WARMUP_TAUS_S if t <= t_max / 2] or [WARMUP_TAUS_S[0]]
    x = np.column_stack([pooled, *[np.exp(-t_on / t) for t in taus]])
    gls = StateSpaceGLS(lr.model, prob.cols["t"], prob.usable.session)
    nb = prob.base.shape[1]
    g = gls.gram(np.column_stack([prob.base, x, lr.prob.y[:, lr.axis]]))
    q0 = _q(g, np.arange(nb), prob.n)
    d = [q0 - _q(g, np.r_[np.arange(nb), nb + j], prob.n) for j in range(x.shape[1])]
    j = int(np.argmax(d))
    return x[:, j : j + 1], (None if j == 0 else float(taus[j - 1]))


def heldout_walk(prob: Problem, model: NoiseModel, axis: int, chosen: list[Candidate]) -> np.ndarray:
    """Held-out residual (M,) of baseline + chosen causes + the slow states (a Kalman smoother).

    Per fold, the coefficients are fitted by GLS on the training rows and the slow states (walk,
    flicker bank) are smoothed from the training rows' residual; a held-out row is predicted by both.
    """
    y = prob.y[:, axis]
    out = np.empty_like(y)
    for k in range(prob.n_folds):
        test = prob.fold == k
        if not test.any():
            continue
        x = np.column_stack([prob.base, *[c.folds[k] for c in chosen if c.cause != "random_walk"]])
        gls = StateSpaceGLS(model, prob.cols["t"], prob.usable.session, (~test).astype(float))
        g = gls.gram(np.column_stack([x, y]))
        beta = gram_solve(g[:-1, :-1], g[:-1, -1], int((~test).sum()))
        r = y - x @ beta
        out[test] = (r - gls.smooth(r))[test]
    return out


def smooth_full(prob: Problem, model: NoiseModel, axis: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GLS fit of y on x (M, P) on all rows: (coefficients, slow-state estimate (M,) [deg/s])."""
    y = prob.y[:, axis]
    gls = StateSpaceGLS(model, prob.cols["t"], prob.usable.session)
    g = gls.gram(np.column_stack([x, y]))
    beta = gram_solve(g[:-1, :-1], g[:-1, -1], prob.n)
    return beta, gls.smooth(y - x @ beta)


# --- the random walk by a variance-component likelihood ratio (issue 12, s12walk) -------------------

WALK_GRID_STEP_DEC = 0.5
"""Step of the walk-intensity grid [decades of q]; the best grid point is refined by a parabola."""
WALK_GRID_BELOW_DEC = 1.0
"""How far below q0 = s2 / (fs T^2) the grid starts [decades]: q0 is the walk whose spread over a
session T equals the standard error of the session's mean under the white level s2, so a walk well
below it cannot be seen."""


def fast_part(model: NoiseModel) -> NoiseModel:
    """The error model without its slow states: white + colour only (the walk test's null)."""
    return NoiseModel(model.rate_hz, model.white_var, list(model.fast), 0.0)


def with_walk(model: NoiseModel, q: float) -> NoiseModel:
    """``model`` (white + colour) plus a random walk of intensity q [(deg/s)^2 / s]."""
    return NoiseModel(model.rate_hz, model.white_var, list(model.gm), float(q))


def _reml_terms(gls: StateSpaceGLS, x: np.ndarray, ys: np.ndarray, n: int, rank: int
                ) -> tuple[np.ndarray, float]:
    """(Q per column of ys (K,), log det V + log pdet X'V^-1X) under one error model.

    Q is the GLS residual quadratic form of each y on x; the pseudo-determinant takes the ``rank``
    largest eigenvalues of the column-scaled Gram (the scaling is V-independent, so it cancels in a
    likelihood ratio)."""
    p = x.shape[1]
    g = gls.gram(np.column_stack([x, ys]))
    gx, gy = g[:p, :p], g[:p, p:]
    beta = gram_solve(gx, gy, n)
    q = np.diag(g[p:, p:]) - np.einsum("pk,pk->k", gy, beta)
    scale = np.sqrt(np.maximum(np.sum(x * x, axis=0), 1e-300))
    lam = np.linalg.eigvalsh(gx / np.outer(scale, scale))
    logdet_x = float(np.sum(np.log(np.maximum(lam[-rank:], 1e-300)))) if rank else 0.0
    return q, float(gls.logdet_v) + logdet_x


def walk_grid(prob: Problem, model: NoiseModel) -> np.ndarray:
    """Walk intensities q [(deg/s)^2 / s] the profile likelihood is evaluated at (ascending)."""
    s2 = model.lowfreq_white_var
    spans = [float(np.ptp(prob.cols["t"][prob.usable.session == s])) for s in np.unique(prob.usable.session)]
    span = max(float(np.mean(spans)), 10.0 / model.rate_hz)
    lo = np.log10(s2 / (model.rate_hz * span**2)) - WALK_GRID_BELOW_DEC
    hi = np.log10(s2 * model.rate_hz)
    return 10.0 ** np.arange(lo, hi + 1e-9, WALK_GRID_STEP_DEC)


@dataclass
class WalkLR:
    """The variance-component likelihood ratio for a random walk on one axis (see ``walk_lr``)."""

    q_hat: float  # [(deg/s)^2 / s], 0 when the likelihood is largest without a walk
    d: float
    p_value: float
    null: NoiseModel  # white + colour (the model without slow states)

    @property
    def model(self) -> NoiseModel:
        """The alternative at its estimate: white + colour + walk(q_hat)."""
        return with_walk(self.null, self.q_hat)


def walk_profile(prob: Problem, null: NoiseModel, x: np.ndarray, ys: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Restricted log-likelihood ratio D (K,) and its argmax q (K,) of a walk against none, per column.

    l(q) = -1/2 [Q(q) + log det V(q) + log pdet X'V(q)^-1 X] (REML: the mean model is the same under
    both hypotheses, so the restricted likelihoods are comparable, and they do not take the
    regression's absorbed share of the wander for missing walk power). Evaluated on ``walk_grid``;
    the best grid point of a single column is refined by a parabola in log q (one more evaluation).
    Several columns ys (M, K) share every banded factorisation, so simulated draws cost one solve per
    grid point; they keep their grid point (a refinement would need one more solve per draw).
    """
    ys = ys.reshape(ys.shape[0], -1)
    n = prob.n
    _, rank = gram_solve(x.T @ x, x.T @ ys[:, :1], n, return_rank=True)
    t, sess = prob.cols["t"], prob.usable.session

    def ll(q: float) -> tuple[np.ndarray, np.ndarray]:
        gls = StateSpaceGLS(with_walk(null, q), t, sess)
        qf, logdet = _reml_terms(gls, x, ys, n, rank)
        return -0.5 * (qf + logdet), qf

    d, q_hat, _, _ = _grid_max(ll, walk_grid(prob, null))
    return d, q_hat


def _grid_max(ll, grid: np.ndarray  # noqa: ANN001 (ll: q -> (l (K,), aux (K,)))
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Maximise a per-column log-likelihood ll(q) over the walk intensity q on ``grid``, the shared
    search of ``walk_profile`` and ``walk_profile_profiled``.

    ll returns (l (K,), aux (K,)), aux a by-product the caller needs at the argmax (the REML
    quadratic form). A single column's best grid point is refined by a parabola through it and its
    neighbours in log q (one more evaluation); several columns (simulated draws) keep the grid.
    Returns D = 2 (l(q_hat) - l(0)) and q_hat (0 where D <= 0), aux at q_hat and aux at q = 0.
    """
    l0, aux0 = ll(0.0)
    evals = [ll(q) for q in grid]
    ls = np.array([e[0] for e in evals])  # (G, K)
    auxs = np.array([e[1] for e in evals])
    best = np.argmax(ls, axis=0)
    cols = np.arange(ls.shape[1])
    d = 2.0 * (ls[best, cols] - l0)
    q_hat = grid[best].astype(float)
    aux = auxs[best, cols]
    j = int(best[0])
    if ls.shape[1] == 1 and 0 < j < len(grid) - 1:
        a, b, c = ls[j - 1, 0], ls[j, 0], ls[j + 1, 0]
        den = a - 2 * b + c
        if den < 0:
            qv = float(q_hat[0] * 10.0 ** (0.5 * (a - c) / den * WALK_GRID_STEP_DEC))
            lv, auxv = ll(qv)
            if 2 * (lv[0] - l0[0]) > d[0]:
                d[0], q_hat[0], aux[0] = 2 * (lv[0] - l0[0]), qv, auxv[0]
    pos = d > 0
    return np.where(pos, d, 0.0), np.where(pos, q_hat, 0.0), aux, aux0


WALK_NULL = "profiled"
"""How the walk test's null level is set: "profiled" (``walk_profile_profiled``: the low-frequency
white level re-estimated by REML with the walk, on block means) or "allan" (``walk_profile``: the
Allan fit's white + colour, held)."""
WALK_BLOCK_SAMPLES = 32
"""Samples per block mean of the profiled walk test: 8 x ``FAST_SAMPLES``, so the colour (correlation
time <= 4 samples) is averaged to white noise at its low-frequency level."""
WALK_MIN_BLOCKS = 40
"""Fewest blocks per session (median) the profiled test keeps; shorter sessions get shorter blocks."""

WALK_MIN_BLOCK_SAMPLES = 8
"""Shortest block the profiled test uses (2 x ``FAST_SAMPLES``); with shorter sessions it falls back
to the held Allan level (``walk_profile``): block means of fewer samples keep the colour's
correlation, and a level profiled on them is pulled below the low-frequency one."""


def block_size(prob: Problem) -> int:
    """Samples per block mean for ``walk_profile_profiled`` (see ``WALK_BLOCK_SAMPLES``)."""
    counts = np.bincount(np.unique(prob.usable.session, return_inverse=True)[1])
    return int(max(1, min(WALK_BLOCK_SAMPLES, int(np.median(counts)) // WALK_MIN_BLOCKS)))


def block_means(prob: Problem, x: np.ndarray, ys: np.ndarray, m: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t [s], session, x, ys) averaged over consecutive blocks of m used samples within each session.

    Each session's rows are cut into whole blocks from its start (a last partial block is dropped:
    its mean would have another variance). Why: the GLS takes the colour as white noise at its
    low-frequency level, right for slow regressors but not for the per-sample scale; a scale
    profiled by REML on the samples is pulled to the per-sample variance (on mikoff imu0 x 0.42 of
    the low-frequency level), and the walk then takes the difference (D ~ 500 on every path). The
    block means of the colour are white at the low-frequency level / m.
    """
    sess = prob.usable.session
    t = prob.cols["t"]
    rows = []
    for s in np.unique(sess):
        idx = np.flatnonzero(sess == s)
        rows.append(idx[: (idx.size // m) * m])
    idx = np.concatenate(rows)

    def mean(a: np.ndarray) -> np.ndarray:
        a = a[idx]
        return np.add.reduceat(a, np.arange(0, a.shape[0], m), axis=0) / m

    return mean(t), sess[idx][::m], mean(x), mean(ys)


def walk_profile_profiled(prob: Problem, null: NoiseModel, x: np.ndarray, ys: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """D (K,), q_hat (K,) [(deg/s)^2/s] and the REML low-frequency white level s2_hat (K,)
    [(deg/s)^2 per sample] of a walk against none, per column, with the level profiled under BOTH
    hypotheses.

    Why (issue 12, s13white): the Allan fit of a log with a walk gives part of the walk's power to
    the colour members, so the held null's level is 11-20 % high (mikoff imu0 x) and D drops. Here
    the level is a free scale: on block means (``block_means``) V = s (I + lam W), W the walk's
    covariance per unit intensity; for each lam the REML scale is s = Q(lam) / (n - r), and the
    profile l(lam) = -1/2 [(n - r) log Q(lam) + log det(I + lam W) + log pdet X'V^-1X] (+ const);
    D = 2 (max l(lam) - l(0)). lam runs over ``walk_grid`` of the Allan null (in units of its
    level), then a parabola for a single column. The null's colour sets only the block size.
    """
    ys = ys.reshape(ys.shape[0], -1)
    m = block_size(prob)
    if m < WALK_MIN_BLOCK_SAMPLES:  # too short for block means: the held level (see the constant)
        d, q = walk_profile(prob, null, x, ys)
        return d, q, np.full(d.shape, null.lowfreq_white_var)
    t, sess, xb, yb = block_means(prob, x, ys, m)
    n = t.size
    _, rank = gram_solve(xb.T @ xb, xb.T @ yb[:, :1], n, return_rank=True)
    dof = max(n - rank, 1)
    ref = null.lowfreq_white_var / m  # block-mean variance of the Allan null [(deg/s)^2]
    unit = NoiseModel(null.rate_hz / m, ref, [], 0.0)

    def ll(q: float) -> tuple[np.ndarray, np.ndarray]:
        gls = StateSpaceGLS(with_walk(unit, q), t, sess)
        qf, logdet = _reml_terms(gls, xb, yb, n, rank)
        qf = np.maximum(qf, 1e-300)
        return -0.5 * (dof * np.log(qf) + logdet), qf

    d, q_hat, qf, qf0 = _grid_max(ll, walk_grid(prob, null))
    scale = np.where(d > 0, qf, qf0) / dof  # the REML scale s (dimensionless) at q_hat, or at 0
    # the walk's intensity is relative to the reference level: V = s (ref I + q W) -> q s
    return d, q_hat * scale, scale * null.lowfreq_white_var


def scaled(model: NoiseModel, s2: float) -> NoiseModel:
    """``model`` (white + colour) with every variance scaled so its low-frequency level is s2."""
    c = s2 / max(model.lowfreq_white_var, 1e-300)
    return NoiseModel(model.rate_hz, model.white_var * c, [(t, v * c) for t, v in model.gm], model.walk_q * c)


def walk_statistic(prob: Problem, null: NoiseModel, x: np.ndarray, ys: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """D (K,) and q_hat (K,) of the walk test as ``WALK_NULL`` sets it (the oracle's and tests' entry)."""
    if WALK_NULL == "profiled":
        d, q, _ = walk_profile_profiled(prob, null, x, ys)
        return d, q
    return walk_profile(prob, null, x, ys)


def chibar_p(d: float) -> float:
    """p-value of a variance component on its boundary: the 50:50 mixture of 0 and chi-square(1)."""
    return float(0.5 * stats.chi2.sf(d, 1)) if d > 0 else 1.0


def walk_lr(lr: AxisLR, chosen: list[str]) -> WalkLR:
    """Is there a random walk on this axis, given baseline + ``chosen`` causes? (cached on ``lr``)

    The null is the axis' point error model without its slow states (white + colour, fitted to the
    Allan octaves of the model-so-far residual); the alternative adds a random walk whose intensity q
    is re-estimated by (restricted) maximum likelihood, the rest of the model held. D = 2 (l(q_hat) -
    l(0)) is referred to the boundary null (chi-bar-square, 50:50 of 0 and chi-square(1)), which is
    conservative for a walk (q_hat = 0 happens more than half the time under the null in a time
    series: the pile-up of the local-level model). Unlike the held-out t-test over blocks this
    needs no slow power in the Allan fit and weighs every sample, not a handful of blocks.
    """
    key = ("walk", *chosen)
    if key not in lr.walks:
        null = fast_part(lr.point_model_for(chosen))
        x = lr.design(chosen)
        y = lr.prob.y[:, lr.axis]
        if WALK_NULL == "profiled":
            d, q, s2 = walk_profile_profiled(lr.prob, null, x, y)
            null = scaled(null, float(s2[0]))
        else:
            d, q = walk_profile(lr.prob, null, x, y)
        lr.walks[key] = WalkLR(float(q[0]), float(d[0]), chibar_p(float(d[0])), null)
    return lr.walks[key]


# --- covariates weighed against the walk (outside check H1, 2026-11-27) -----------------------------

def _walk_profiled_ml(lr: AxisLR, null: NoiseModel, causes: list[str] | tuple[str, ...]) -> float | None:
    """The largest log-likelihood (ML, up to a constant shared by every design) of baseline + ``causes``
    on this axis' block means, with the white level and the walk intensity both re-estimated
    (``walk_profiled_ml`` of their design)."""
    return walk_profiled_ml(lr, null, lr.design(causes))


def walk_profiled_ml(lr: AxisLR, null: NoiseModel, x: np.ndarray) -> float | None:
    """The largest log-likelihood (ML, up to a constant shared by every design) of the design ``x``
    (M, P; the baseline and cause columns) on this axis' block means, with the white level and the
    walk intensity both re-estimated.

    V = s (I + lam W) on the block means (see ``block_means``, ``walk_profile_profiled``); the scale s
    is profiled out (s = Q / n), lam runs over ``walk_grid`` of ``null`` (0 included, a parabola
    refines the best point). ML, not REML: the two designs compared differ, and restricted
    likelihoods of different mean models are not comparable. None when the sessions are too short
    for block means (``WALK_MIN_BLOCK_SAMPLES``).
    """
    prob = lr.prob
    m = block_size(prob)
    if m < WALK_MIN_BLOCK_SAMPLES:
        return None
    t, sess, xb, yb = block_means(prob, x, prob.y[:, lr.axis][:, None], m)
    n = t.size
    p = xb.shape[1]
    unit = NoiseModel(null.rate_hz / m, null.lowfreq_white_var / m, [], 0.0)

    def ll(q: float) -> tuple[np.ndarray, np.ndarray]:
        gls = StateSpaceGLS(with_walk(unit, q), t, sess)
        g = gls.gram(np.column_stack([xb, yb]))
        beta = gram_solve(g[:p, :p], g[:p, p:], n)
        qf = np.maximum(np.diag(g[p:, p:]) - np.einsum("pk,pk->k", g[:p, p:], beta), 1e-300)
        return -0.5 * (n * np.log(qf) + gls.logdet_v), qf

    l0 = float(ll(0.0)[0][0])
    d, _, _, _ = _grid_max(ll, walk_grid(prob, null))
    return l0 + 0.5 * float(d[0])


def test_against_walk(lr: AxisLR, chosen: list[str], causes: tuple[str, ...]) -> tuple[float, float] | None:
    """(D, p-value with the look-elsewhere factors) for adding the covariate ``causes`` to ``chosen``
    with the random walk's intensity (and the white level) re-estimated under BOTH hypotheses.

    Why (outside check H1, 2026-11-27): ``AxisLR.test`` holds the slow states of the error model fitted
    to a residual that still holds the effect, so a temperature effect on a white log is partly
    taken as wander: temperature p = 0.0079 there, then the walk, tested on what the covariates
    left, took the same signal (p = 9e-24) and random_walk was named for a temperature effect. Here
    the walk can only keep what the covariates, fitted with it, leave: on that log D = 30 (p = 2.5e-7)
    and the walk given temperature has D = 0. On 360 axes of flicker and "all three" nulls (seeds
    32000-32059) the smallest p of a single covariate was 8.4e-4 (above ``ALPHA``), because the
    walk, re-estimated, takes what wanders. D is chi-square with the causes' column count (ML
    likelihood ratio of nested mean models, the variance parameters profiled under both). None
    when the sessions are too short for block means. Cached on ``lr``.
    """
    key = (("walk-profiled", *chosen), "+".join(causes))
    if key in lr.tests:
        return lr.tests[key]
    null = fast_part(lr.point_model_for(chosen))
    l0 = _walk_profiled_ml(lr, null, chosen)
    l1 = _walk_profiled_ml(lr, null, [*chosen, *causes])
    if l0 is None or l1 is None:
        return None
    d = max(2.0 * (l1 - l0), 0.0)
    k = max(sum(int(lr.cols[c].shape[1]) for c in causes), 1)
    look = float(np.prod([lr.look_elsewhere.get(c, 1.0) for c in causes]))
    lr.tests[key] = (float(d), float(min(1.0, look * stats.chi2.sf(d, k))))
    return lr.tests[key]
