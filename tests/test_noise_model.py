"""The truth model's sensor noise: coloured, flicker (bias instability), filter, quantisation."""

from __future__ import annotations

import numpy as np
import pytest

from gyrocal.model.allan import FLICKER_FLOOR, allan_curve, gauss_markov_avar, read_noise_terms
from gyrocal.sim.schedule import still, tumble
from gyrocal.sim.truth import DPH, Effects, SessionStream, TruthModel, flicker_components


def _noisy() -> TruthModel:
    e = Effects(bias_instability_dps=np.array([20, 10, 5]) * DPH, gm_dps=np.full(3, 0.003), gm_tau_s=0.05,
                lowpass_hz=20.0, quant_lsb_dps=np.array([1 / 131, 0.0, 0.001]),
                random_walk_dps_per_sqrt_s=np.full(3, 1e-4))
    return TruthModel(effects=e)


def test_stream_with_every_noise_is_chunk_size_invariant_and_seeded() -> None:
    m = _noisy()
    whole = SessionStream(m, tumble(), 100.0, seed=5, boot=2).chunk(3000)
    s = SessionStream(m, tumble(), 100.0, seed=5, boot=2)
    parts = [s.chunk(k) for k in (1, 7, 992, 1000, 1000)]
    for key in ("wx", "wy", "wz", "drift_wx", "drift_wz"):
        np.testing.assert_allclose(np.concatenate([p[key] for p in parts]), whole[key], rtol=0, atol=1e-15)
    other = SessionStream(m, tumble(), 100.0, seed=6, boot=2).chunk(3000)
    assert not np.array_equal(other["wy"], whole["wy"])


def test_defaults_leave_the_baseline_stream_unchanged() -> None:
    assert not Effects().any()
    a = SessionStream(TruthModel(), tumble(), 100.0, seed=1, boot=0).chunk(500)
    # the baseline by hand: the same generators as before the noise model existed
    m = TruthModel()
    rng = np.random.default_rng([1, 0, 1])
    noise = rng.normal(0.0, m.noise_dps, (500, 3))
    np.testing.assert_allclose(a["wx"] - a["ref_wx"] - a["drift_wx"], noise[:, 0], rtol=0, atol=1e-17)


def test_quantisation_puts_the_output_on_the_lsb_grid() -> None:
    c = SessionStream(_noisy(), tumble(), 100.0, seed=0, boot=0).chunk(2000)
    np.testing.assert_allclose(c["wx"] * 131, np.round(c["wx"] * 131), atol=1e-9)
    np.testing.assert_allclose(c["wz"] * 1000, np.round(c["wz"] * 1000), atol=1e-9)
    assert np.abs(c["wy"] * 131 - np.round(c["wy"] * 131)).max() > 0.1


def test_gauss_markov_noise_has_its_std_and_correlation() -> None:
    e = Effects(gm_dps=np.full(3, 0.01), gm_tau_s=0.2)
    c = SessionStream(TruthModel(noise_dps=0.0, effects=e), still(), 100.0, seed=2, boot=0).chunk(60_000)
    x = c["wx"] - c["drift_wx"]
    assert np.std(x) == pytest.approx(0.01, rel=0.05)
    r1 = np.corrcoef(x[:-1], x[1:])[0, 1]
    assert r1 == pytest.approx(np.exp(-0.01 / 0.2), abs=0.01)
    assert np.array_equal(c["drift_wx"], c["drift_wx"][0] + 0 * c["drift_wx"])   # noise, not drift


def test_lowpass_lowers_the_sample_std_but_keeps_the_arw() -> None:
    fs, sigma = 100.0, 0.01
    m = TruthModel(noise_dps=sigma, effects=Effects(lowpass_hz=5.0))
    c = SessionStream(m, still(), fs, seed=3, boot=0).chunk(60_000)
    x = c["wy"] - c["drift_wy"]
    a = 1 - np.exp(-2 * np.pi * 5.0 / fs)
    assert np.std(x) == pytest.approx(sigma * np.sqrt(a / (2 - a)), rel=0.03)
    # first differences read the white level low under colour (issue 12 item 3)
    assert np.std(np.diff(x)) / np.sqrt(2) < 0.5 * sigma
    arw = read_noise_terms(allan_curve(x, fs)).arw.value
    assert arw == pytest.approx(sigma / np.sqrt(fs), rel=0.1)


def test_flicker_components_give_a_flat_floor_analytically() -> None:
    corr, w = flicker_components((1.0, 1000.0))
    taus = np.geomspace(1.0, 1000.0, 40)
    adev = np.sqrt(sum(gauss_markov_avar(taus, wk, t) for t, wk in zip(corr, w, strict=True)))
    np.testing.assert_allclose(adev, FLICKER_FLOOR, rtol=0.06)
    with pytest.raises(ValueError, match="flicker_band_s"):
        flicker_components((5.0, 1.0))


@pytest.mark.slow
def test_simulated_bias_instability_reads_back_from_the_allan_floor() -> None:
    fs, b = 10.0, 30 * DPH
    e = Effects(bias_instability_dps=np.full(3, b), flicker_band_s=(1.0, 300.0))
    m = TruthModel(noise_dps=0.002, effects=e)
    floors = []
    for seed in range(3):
        c = SessionStream(m, still(), fs, seed=seed, boot=0).chunk(60_000)
        cur = allan_curve(c["wx"] - c["ref_wx"], fs, max_tau_s=300.0)
        sel = (cur.tau_s >= 3.0) & (cur.tau_s <= 100.0)
        floors.append(cur.adev[sel])
        terms = read_noise_terms(cur)
        assert terms.bias_instability.value == pytest.approx(b, rel=0.35)
    mean = np.mean(floors, axis=0)
    np.testing.assert_allclose(mean, FLICKER_FLOOR * b, rtol=0.25)
