"""The Kalman filter with a bias state (method kf): two forms agree, a walk is tracked, RLS at q = 0."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gyrocal.errors import ConfigError
from gyrocal.model.bias_kalman import GM_PEAK, BiasKalman, BiasModel
from gyrocal.model.estimator import Estimator
from gyrocal.model.identifiability import determined_part
from gyrocal.model.methods import make_estimator
from gyrocal.model.prep import gravity_direction
from gyrocal.model.terms import SEED000_TERMS, TermSpec
from gyrocal.sim.schedule import still, tumble
from gyrocal.sim.truth import DPH, Effects, SessionStream, TruthModel

SPEC = TermSpec.parse(SEED000_TERMS)
WALK = BiasModel(random_walk_dps_per_sqrt_s=np.array([2e-4, 1e-4, 5e-5]),
                 gm_sigma_dps=np.array([1e-3, 2e-3, 0.0]), gm_tau_s=np.array([50.0, 20.0, 10.0]),
                 noise_dps=np.full(3, 0.002))


def _stream(model: TruthModel, schedule, n: int, seed: int = 4, rate: float = 100.0) -> dict:
    s = SessionStream(model, schedule, rate, seed=seed, boot=0)
    c = s.chunk(n)
    acc = np.column_stack([c[f"a{a}"] for a in "xyz"])
    g = gravity_direction(acc)
    keep = c["still"].astype(bool)
    return {"phi": SPEC.design({"gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]})[keep],
            "y": np.column_stack([c[f"w{a}"] for a in "xyz"])[keep], "t": c["t"][keep],
            "drift": np.column_stack([c[f"drift_w{a}"] for a in "xyz"])[keep], "bias": s.bias_dps}


@pytest.fixture(scope="module")
def walk_tumble() -> dict:
    e = Effects(random_walk_dps_per_sqrt_s=np.full(3, 2e-4))
    return _stream(TruthModel(effects=e), tumble(), 4_000)


def _reference_kf(est: BiasKalman, z: np.ndarray, meas: np.ndarray, t: np.ndarray) -> np.ndarray:
    """A textbook filterpy-style KF, one axis at a time, plain matrices: the state after all samples."""
    bm, p = est.bias, len(est.spec)
    n = est.n_state
    out = np.zeros((n, 3))
    for a in range(3):
        x = np.zeros(n)
        P = np.zeros((n, n))
        P[:p, :p] = np.eye(p) * est.prior_sigma ** 2
        R = bm.noise_dps[a] ** 2
        last = None
        for k in range(len(z)):
            dt = est.dt_s if last is None else t[k] - last
            last = t[k]
            F, Q = np.eye(n), np.zeros((n, n))
            if est.i_rw is not None:
                Q[est.i_rw, est.i_rw] = bm.random_walk_dps_per_sqrt_s[a] ** 2 * dt
            if est.i_gm is not None:
                f = np.exp(-dt / bm.gm_tau_s[a])
                F[est.i_gm, est.i_gm] = f
                Q[est.i_gm, est.i_gm] = bm.gm_sigma_dps[a] ** 2 * (1 - f * f)
            H = np.concatenate([z[k], np.ones(n - p)])[None, :]
            x = F @ x                                    # x = F x
            P = F @ P @ F.T + Q                          # P = F P F' + Q
            y = meas[k, a] - H @ x                       # y = z - H x
            S = H @ P @ H.T + R                          # S = H P H' + R
            K = P @ H.T @ np.linalg.inv(S)               # K = P H' S^-1
            x = x + (K @ y)                              # x = x + K y
            IKH = np.eye(n) - K @ H
            P = IKH @ P @ IKH.T + K * R @ K.T            # Joseph form
        out[:, a] = x
    return out


def test_batched_filter_equals_a_textbook_kalman_filter(walk_tumble: dict) -> None:
    d = {k: v[:800] for k, v in walk_tumble.items() if k != "bias"}
    # a tight prior keeps P well conditioned, so the two forms agree to rounding (with the default
    # 1 deg/s prior they agree to ~1e-10 deg/s along the directions the first samples barely excite)
    est = BiasKalman(SPEC, bias=WALK, prior_sigma_dps=0.05)
    est.update_many(d["phi"], d["y"], d["t"])
    z = d["phi"] * est.norm.a - est.norm.c
    ref = _reference_kf(est, z, d["y"], d["t"])
    np.testing.assert_allclose(est.X, ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("bias", [WALK, BiasModel()], ids=["walk+gm, fixed R", "no bias state, adaptive R"])
def test_per_sample_update_equals_update_many_and_warm_start_continues(walk_tumble: dict, bias) -> None:
    phi, y, t = (walk_tumble[k][:2000].copy() for k in ("phi", "y", "t"))
    phi[10, 3], y[20, 1], t[30] = np.nan, 5000.0, t[29] - 1.0          # skipped samples
    a, b = BiasKalman(SPEC, bias=bias), BiasKalman(SPEC, bias=bias)
    ea = np.array([a.update(p, yy, tt) for p, yy, tt in zip(phi, y, t, strict=True)])
    eb = b.update_many(phi, y, t)
    np.testing.assert_allclose(ea, eb, rtol=0, atol=1e-12, equal_nan=True)
    np.testing.assert_allclose(a.coefficients, b.coefficients, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.P, b.P, rtol=0, atol=1e-12)
    c = Estimator.from_state(json.loads(json.dumps(b.state())))
    assert isinstance(c, BiasKalman)
    nxt = slice(2000, 2600)
    b.update_many(walk_tumble["phi"][nxt], walk_tumble["y"][nxt], walk_tumble["t"][nxt])
    c.update_many(walk_tumble["phi"][nxt], walk_tumble["y"][nxt], walk_tumble["t"][nxt])
    np.testing.assert_array_equal(b.coefficients, c.coefficients)


def test_a_bias_random_walk_is_tracked_where_rls_goes_stale() -> None:
    q = 3e-4                                                             # deg/s/sqrt(s)
    m = TruthModel(effects=Effects(random_walk_dps_per_sqrt_s=np.full(3, q)))
    d = _stream(m, still(), 12_000, seed=9, rate=20.0)                   # 600 s at one pose
    names = ["1"]
    kf = make_estimator("kf", names, bias={"random_walk_dps_per_sqrt_s": [q] * 3, "gm_sigma_dps": [0] * 3,
                                           "gm_tau_s": [1] * 3, "noise_dps": None})
    rls = make_estimator("rls", names)
    ones = np.ones((len(d["y"]), 1))
    track = np.empty_like(d["y"])
    for i in range(0, len(d["y"]), 100):                                # read as the daemon would
        sl = slice(i, i + 100)
        kf.update_many(ones[sl], d["y"][sl], d["t"][sl])
        rls.update_many(ones[sl], d["y"][sl], d["t"][sl])
        track[sl] = kf.coefficients[:, 0]
    truth_now = d["drift"][-1]
    err_kf = np.abs(kf.coefficients[:, 0] - truth_now)
    err_rls = np.abs(rls.coefficients[:, 0] - truth_now)
    assert np.all(err_kf < 3 * kf.uncertainty[:, 0] + 1e-12)
    assert np.sqrt(np.mean(err_kf**2)) < 0.25 * np.sqrt(np.mean(err_rls**2))
    lag = np.sqrt(np.mean((track[1000:] - d["drift"][1000:]) ** 2))
    assert lag < 0.2 * np.std(d["drift"][1000:] - d["drift"][1000:].mean())
    np.testing.assert_allclose(kf.noise_dps, 0.002, rtol=0.05)       # R found on line


def test_gravity_coefficients_converge_as_with_rls_when_the_walk_is_zero() -> None:
    d = _stream(TruthModel(), tumble(), 10_800, seed=11)
    rls = make_estimator("rls")
    rls.update_many(d["phi"], d["y"], d["t"])
    sig = rls.uncertainty
    ident = rls.identifiability
    for bias, tol in ((BiasModel(noise_dps=np.full(3, 0.002)), 0.01), (BiasModel(), 0.5)):
        kf = make_estimator("kf", bias=bias)
        kf.update_many(d["phi"], d["y"], d["t"])
        diff = determined_part(kf.coefficients - rls.coefficients, ident)
        det = np.isfinite(sig)
        assert np.all(np.abs(diff[det]) < tol * sig[det])
        assert kf.convergence().converged, kf.convergence().reason
        np.testing.assert_array_equal(np.isinf(kf.uncertainty), np.isinf(sig))
        np.testing.assert_allclose(kf.uncertainty[det], sig[det], rtol=0.3)


def test_spec_from_analyze_and_bias_instability_conversion() -> None:
    doc = {"terms": list(SEED000_TERMS),
           "random_walk": {"dps_per_sqrt_s": {"x": 1e-4, "y": 2e-4, "z": 0.0}, "knot_s": 30.0},
           "bias_instability": {"dps": {"x": 20 * DPH, "y": 10 * DPH, "z": 5 * DPH}, "tau_s": 400.0},
           "noise_dps": {"x": 0.01, "y": 0.01, "z": 0.02}}
    bm = BiasModel.from_spec(doc, "OUT.terms.yaml")
    np.testing.assert_allclose(bm.random_walk_dps_per_sqrt_s, [1e-4, 2e-4, 0.0])
    np.testing.assert_allclose(bm.gm_sigma_dps * GM_PEAK / 0.6643, [20 * DPH, 10 * DPH, 5 * DPH], rtol=1e-3)
    np.testing.assert_allclose(bm.gm_tau_s, 400.0 / 1.8926)
    np.testing.assert_allclose(bm.noise_dps, [0.01, 0.01, 0.02])
    old = {"causes": {"random_walk": {"axes": ["x"], "params": {"dps_per_sqrt_s": {"x": 3e-4}}}}}
    assert BiasModel.from_spec(old).random_walk_dps_per_sqrt_s[0] == 3e-4
    with pytest.raises(ConfigError, match="OUT.terms.yaml: field 'gauss_markov' needs sigma_dps and tau_s"):
        BiasModel.from_spec({"gauss_markov": {"sigma_dps": 1e-3}}, "OUT.terms.yaml")
    with pytest.raises(ConfigError, match="random_walk.dps_per_sqrt_s"):
        BiasModel.from_spec({"random_walk": {"dps_per_sqrt_s": {"x": -1}}}, "f.yaml")


def test_daemon_config_kf_loads_the_intensities_from_the_terms_file(tmp_path) -> None:
    from gyrocal.daemon.config import load_config
    from gyrocal.daemon.learner import make_learner

    (tmp_path / "out.terms.yaml").write_text(
        "terms: ['1', gx, gy, gz]\n"
        "random_walk: {dps_per_sqrt_s: {x: 1.0e-4, y: 2.0e-4, z: 0.0}, knot_s: 30}\n"
        "noise_dps: {x: 0.01, y: 0.01, z: 0.01}\n", encoding="utf-8")
    cfg_path = tmp_path / "kf.yaml"
    cfg_path.write_text("virtual_unit: {enabled: true}\nestimator: {method: kf, terms: out.terms.yaml}\n",
                        encoding="utf-8")
    learner = make_learner(load_config(cfg_path), None)
    assert isinstance(learner.est, BiasKalman)
    np.testing.assert_allclose(learner.est.bias.random_walk_dps_per_sqrt_s, [1e-4, 2e-4, 0.0])
    phi = np.column_stack([np.ones(50), np.zeros(50), np.zeros(50), np.ones(50)])
    learner.update_many(phi, np.full((50, 3), 0.01), np.arange(50) * 0.01)
    assert learner.est.kf_t == pytest.approx(0.49)
    (tmp_path / "out.terms.yaml").write_text("terms: ['1']\nrandom_walk: {dps_per_sqrt_s: {x: -1}}\n",
                                             encoding="utf-8")
    with pytest.raises(ConfigError, match=r"out.terms.yaml: field 'random_walk.dps_per_sqrt_s'"):
        load_config(cfg_path)


@pytest.mark.parametrize("horizon_s", [0.0, 300.0])
def test_the_wander_left_after_a_push_matches_simulated_paths(horizon_s: float) -> None:
    """``wander_dps`` is the push gate's floor: the RMS over the next H seconds of the bias's move away
    from what is pushed now. Checked against 4000 simulated walk + Gauss-Markov paths (exact
    discretisation), the pushed value being the walk's and the GM's part as the filter weighs it."""
    q, s, T, H, dt = 1e-4, 3e-3, 150.0, 600.0, 1.0
    bias = BiasModel(random_walk_dps_per_sqrt_s=np.full(3, q), gm_sigma_dps=np.full(3, s),
                     gm_tau_s=np.full(3, T))
    kf = BiasKalman(SEED000_TERMS, bias=bias, horizon_s=horizon_s)
    rng = np.random.default_rng(8)
    n_paths, steps = 4000, int(H / dt)
    a = np.exp(-dt / T)
    gm0 = rng.normal(0.0, s, n_paths)
    walk = np.cumsum(rng.normal(0.0, q * np.sqrt(dt), (steps, n_paths)), axis=0)
    gm = np.empty((steps, n_paths))
    g = gm0
    for k in range(steps):
        g = a * g + rng.normal(0.0, s * np.sqrt(1 - a * a), n_paths)
        gm[k] = g
    w_p = 1.0 if horizon_s == 0 else T / horizon_s * (1 - np.exp(-horizon_s / T))
    moved = walk + gm - w_p * gm0  # the walk starts at its pushed value
    mc = float(np.sqrt(np.mean(moved**2)))
    np.testing.assert_allclose(kf.wander_dps(H), mc, rtol=0.03)
    assert np.all(BiasKalman(SEED000_TERMS).wander_dps(H) == 0)  # no wander model: no floor
