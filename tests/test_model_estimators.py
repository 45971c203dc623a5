"""Estimators: RLS = batch LS, block = loop, warm start, bad input, LMS convergence, divergence."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from gyrocal.model.estimator import Estimator
from gyrocal.model.identifiability import determined_part, split_subspaces
from gyrocal.model.methods import LMS, METHODS, BatchLS, lstsq_reference, make_estimator
from gyrocal.model.normalise import Normaliser
from gyrocal.model.prep import gravity_direction, segment_ids, still_mask
from gyrocal.model.terms import SEED000_TERMS, TermSpec
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import SessionStream, TruthModel

SPEC = TermSpec.parse(SEED000_TERMS)


@pytest.fixture(scope="module")
def sim() -> dict:
    """Still samples of a simulated tumble (100 Hz, 18 poses, ~4 cycles), with the truth."""
    model = TruthModel()
    stream = SessionStream(model, tumble(), 100.0, seed=7, boot=0)
    cols = stream.chunk(14400)
    acc = np.column_stack([cols[f"a{a}"] for a in "xyz"])
    gyro = np.column_stack([cols[f"w{a}"] for a in "xyz"])
    still = still_mask(cols["t"], gyro, acc)
    g = gravity_direction(acc)
    phi = SPEC.design({"gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]})
    truth = model.coeffs_dps.copy()
    truth[:, 0] += stream.bias_dps  # the switch-on bias adds to d0
    return {"phi": phi[still], "y": gyro[still], "t": cols["t"][still], "truth": truth,
            "segment": segment_ids(still)[still], "true_still": cols["still"]}


def test_still_detector_finds_only_true_rest(sim: dict) -> None:
    assert len(sim["phi"]) > 0.6 * sim["true_still"].sum()
    assert len(np.unique(sim["segment"])) >= 60


def test_rls_without_forgetting_equals_batch_least_squares(sim: dict) -> None:
    norm = Normaliser.from_data(SPEC, sim["phi"], sim["y"])
    rls = make_estimator("rls", SPEC, normaliser=norm)
    for p, y, t in zip(sim["phi"], sim["y"], sim["t"], strict=True):
        rls.update(p, y, t)
    ref = lstsq_reference(norm, sim["phi"], sim["y"], rls.rank_tol)
    np.testing.assert_allclose(rls.coefficients, ref, rtol=1e-9, atol=1e-12)
    batch = BatchLS(SPEC, normaliser=norm)
    batch.update_many(sim["phi"], sim["y"], sim["t"])
    np.testing.assert_allclose(batch.coefficients, ref, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("method", list(METHODS))
def test_block_update_equals_per_sample_loop(sim: dict, method: str) -> None:
    phi, y, t = sim["phi"][:3000].copy(), sim["y"][:3000].copy(), sim["t"][:3000].copy()
    phi[10, 3], y[20, 1], t[30] = np.nan, 5000.0, t[29] - 1.0  # bad samples inside the block
    a, b = make_estimator(method, block=100), make_estimator(method, block=100)
    loop = np.vstack([a.update(phi[i], y[i], t[i]) for i in range(len(phi))])
    block = b.update_many(phi, y, t)
    np.testing.assert_allclose(block, loop, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(b.W, a.W, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(b.R, a.R, rtol=1e-12)
    assert a.counts == b.counts and a.counts["nonfinite"] == a.counts["out_of_range"] == 1
    assert a.counts["time_backwards"] == 1


@pytest.mark.parametrize("method", list(METHODS))
def test_warm_start_from_saved_state_continues_exactly(sim: dict, method: str) -> None:
    phi, y, t = sim["phi"][:4000], sim["y"][:4000], sim["t"][:4000]
    whole = make_estimator(method, forgetting=0.9995) if method == "rls" else make_estimator(method)
    e_whole = whole.update_many(phi, y, t)
    first = make_estimator(method, forgetting=0.9995) if method == "rls" else make_estimator(method)
    e1 = first.update_many(phi[:1777], y[:1777], t[:1777])
    saved = json.loads(json.dumps(first.state(), allow_nan=False))  # strict JSON
    second = Estimator.from_state(saved)
    assert type(second) is type(first)
    e2 = np.vstack([second.update(phi[i], y[i], t[i]) for i in range(1777, 1900)]
                   + [second.update_many(phi[1900:], y[1900:], t[1900:])])
    np.testing.assert_allclose(np.vstack([e1, e2]), e_whole, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(second.coefficients, whole.coefficients, rtol=1e-12, atol=1e-15)
    assert second.counts == whole.counts


@pytest.mark.parametrize("method", list(METHODS))
def test_bad_samples_leave_weights_and_statistics_unchanged(sim: dict, method: str) -> None:
    est = make_estimator(method)
    est.update_many(sim["phi"][:500], sim["y"][:500], sim["t"][:500])
    before = (est.W.copy(), est.coefficients.copy(), est._Zb.copy(), est.R.copy(), est.samples)
    p, y, t = sim["phi"][500], sim["y"][500], sim["t"][500]
    bad = [(np.where(np.arange(10) == 4, np.nan, p), y, t), (p, np.array([0.0, np.inf, 0.0]), t),
           (p, np.array([0.0, 0.0, 2500.0]), t), (p, y, sim["t"][100])]
    for bp, by, bt in bad:
        assert np.all(np.isnan(est.update(bp, by, bt)))
    assert np.all(np.isnan(est.update(p, y, t, accel_g=np.array([0.0, 0.0, 25.0]))))
    est.update_many(np.array([bp for bp, _, _ in bad]), np.array([by for _, by, _ in bad]),
                    np.array([bt for _, _, bt in bad]))
    np.testing.assert_array_equal(est.W, before[0])
    np.testing.assert_array_equal(est.coefficients, before[1])
    np.testing.assert_array_equal(est._Zb, before[2])
    np.testing.assert_array_equal(est.R, before[3])
    assert est.samples == before[4]
    c = est.counts
    assert c["nonfinite"] == 4 and c["out_of_range"] == 3 and c["time_backwards"] == 2


def test_lms_seed_schedule_converges_to_truth_identifiable_part(sim: dict) -> None:
    norm = Normaliser.from_data(SPEC, sim["phi"], sim["y"])
    lms = LMS(SPEC, normaliser=norm, seed=3)
    lms.absorb(sim["phi"], sim["y"], sim["t"])
    from gyrocal.model.prep import FitData
    pairs = FitData(sim["phi"], sim["y"], sim["t"], sim["segment"], len(sim["t"])).segment_means()
    mse = lms.train_seed(*pairs)
    assert mse[-1] < 0.01 * mse[0]
    ident = lms.identifiability
    assert ident.rank == 9
    err = np.abs(determined_part(lms.coefficients - sim["truth"], ident)).max()
    scale = np.abs(determined_part(sim["truth"], ident)).max()
    assert err < 0.1 * scale and err < 2.5 / 3600, (err * 3600, scale * 3600)  # within 2.5 deg/h
    sig = lms.uncertainty
    assert np.isinf(sig[:, [0, 4, 5, 6]]).all() and np.isfinite(sig[:, [1, 2, 3, 7, 8, 9]]).all()


def test_divergent_lms_is_reset_with_a_log_line(sim: dict, caplog: pytest.LogCaptureFixture) -> None:
    lms = make_estimator("lms", block=10)
    lms.W[:] = 1e9
    with caplog.at_level(logging.WARNING, logger="gyrocal.model"):
        lms.update_many(sim["phi"][:10], sim["y"][:10], sim["t"][:10])
    assert lms.counts["resets"] == 1 and np.abs(lms.W).max() < 1e6
    assert "diverged" in caplog.text


def test_rls_reports_converged_with_reason_on_a_tumble(sim: dict) -> None:
    rls = make_estimator("rls", SPEC)
    early = rls.convergence()
    assert not early.converged and "samples" in early.reason
    rls.update_many(sim["phi"], sim["y"], sim["t"])
    status = rls.convergence()
    assert status.converged, status.reason
    assert status.metrics["rank"] == 9


def test_undetermined_combination_is_held_at_the_prior_not_learned(sim: dict) -> None:
    prior = np.zeros((3, 10))
    prior[:, 0], prior[:, 4:7] = 0.01, -0.004  # some earlier calibration [deg/s]
    est = make_estimator("rls", SPEC, prior_dps=prior)
    est.update_many(sim["phi"], sim["y"], sim["t"])
    fresh = make_estimator("rls", SPEC)
    fresh.update_many(sim["phi"], sim["y"], sim["t"])
    null = est.identifiability.null_physical[0]
    np.testing.assert_allclose(null / null[0], [1, 0, 0, 0, -1, -1, -1, 0, 0, 0], atol=1e-9)
    # the prior moved the estimate only along the undetermined direction, and did move it
    diff = est.coefficients - fresh.coefficients
    along = np.outer(diff @ null / (null @ null), null)
    np.testing.assert_allclose(diff, along, atol=1e-12)
    assert np.abs(along).max() > 1e-4
    # the change from the prior lies in the identifiable subspace (normalised coordinates)
    _, _, v_n = split_subspaces(est.R, est.rank_tol)
    w_diff = np.linalg.solve(est.norm.M.T, (est.coefficients - prior).T)
    assert np.abs(v_n.T @ w_diff).max() < 1e-9 * np.abs(w_diff).max()
    est.new_session()
    assert not np.isnan(est.update(sim["phi"][0], sim["y"][0], 0.0)).any()
