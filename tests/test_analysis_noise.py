"""The error model, its banded GLS, the time-stamp repair and the noise causes (issue 12)."""

from __future__ import annotations

import numpy as np
import pytest

from gyrocal.analysis.engine import analyze
from gyrocal.analysis.gls import StateSpaceGLS
from gyrocal.analysis.hidden import add_background, generate
from gyrocal.analysis.noisemodel import NoiseModel, fit_noise
from gyrocal.analysis.timestamps import retime
from gyrocal.logformat import LogData

REGRESSION = {"temperature", "temperature_rate", "warmup", "periodic", "scale_factor"}


def _dense_cov(m: NoiseModel, t: np.ndarray, sess: np.ndarray) -> np.ndarray:
    same = sess[:, None] == sess[None, :]
    c = np.eye(t.size) * m.lowfreq_white_var
    for tau, v in m.slow:
        c += v * np.exp(-np.abs(t[:, None] - t[None, :]) / tau) * same
    t0 = np.array([t[sess == s][0] - 1 / m.rate_hz for s in sess])
    c += m.walk_q * np.minimum(t[:, None] - t0[:, None], t[None, :] - t0[None, :]) * same
    return c


def test_banded_gls_equals_the_dense_covariance_with_gaps_sessions_and_held_out_rows() -> None:
    m = NoiseModel(10.0, 0.01, [(0.1, 0.02), (2.0, 0.005), (20.0, 0.003)], 1e-4)
    t = np.arange(60) / 10.0
    t[30:] += 3.0  # a move between still runs
    sess = (np.arange(60) >= 45).astype(float)
    w = np.ones(60)
    w[10:15] = 0.0
    gls = StateSpaceGLS(m, t, sess, w)
    c = _dense_cov(m, t, sess)
    o = w > 0
    x = np.random.default_rng(1).normal(size=(60, 3))
    ref = np.zeros_like(x)
    ref[o] = np.linalg.solve(c[np.ix_(o, o)], x[o])
    assert np.allclose(gls.vinv(x), ref, atol=1e-9)
    assert np.isclose(gls.logdet_v, np.linalg.slogdet(c[np.ix_(o, o)])[1])
    pred = c[:, o] @ np.linalg.solve(c[np.ix_(o, o)], x[o, 0])
    assert np.allclose(gls.smooth(x[:, 0])[~o], pred[~o], atol=1e-9)


def test_allan_fit_recovers_white_colour_and_walk_where_first_differences_read_low() -> None:
    truth = NoiseModel(100.0, 0.03**2, [(0.02, 0.04**2)], 1e-6)
    x = truth.simulate(200_000, np.random.default_rng(3))
    fit = fit_noise(x, 100.0)
    assert abs(fit.sample_sd / truth.sample_sd - 1) < 0.05
    assert abs(np.sqrt(fit.walk_q / truth.walk_q) - 1) < 0.35
    first_diff = np.std(np.diff(x)) / np.sqrt(2)
    assert first_diff < 0.85 * truth.sample_sd  # the coloured noise fools first differences


def test_bursty_stamps_are_retimed_to_the_sample_clock_and_regular_ones_left_alone() -> None:
    rng = np.random.default_rng(0)
    n = 5000
    clock = np.arange(n) / 99.3
    burst = np.floor(clock / 0.05) * 0.05 + 0.05 + np.arange(n) % 5 * 0.001 + rng.uniform(0, 0.01, n)
    cols, notes = retime({"t": np.sort(burst), "session": np.zeros(n)})
    assert notes and abs(notes[0]["rate_hz"] - 99.3) < 0.05
    assert np.max(np.abs(np.diff(cols["t"]) - 1 / 99.3)) < 1e-6
    _, none = retime({"t": clock + rng.normal(0, 1e-4, n), "session": np.zeros(n)})
    assert none == []


def test_coloured_null_is_named_coloured_noise_and_nothing_else() -> None:
    cols, _ = generate(20_001, causes=[])
    r = analyze(LogData(add_background(cols, "coloured", 20_001), {}, [], "coloured")).result
    assert [f["cause"] for f in r["findings"]] == ["coloured_noise"]
    f = r["findings"][0]
    assert all(v >= 0.02 for v in f["params"]["fidelity_gain_decades"].values())
    assert r["fidelity"]["after"]["x"] < r["fidelity"]["before"]["x"]
    arw = r["allan_terms"]["x"]["arw"]
    assert arw["lo"] <= arw["value"] <= arw["hi"] and arw["value"] > 0


def test_flicker_and_quantised_nulls_raise_no_regression_cause() -> None:
    for kind, seed in (("flicker", 20_003), ("quantised", 20_004)):
        cols, _ = generate(seed, causes=[])
        r = analyze(LogData(add_background(cols, kind, seed), {}, [], kind)).result
        assert not REGRESSION & {f["cause"] for f in r["findings"]}, (kind, r["findings"])


def test_fidelity_is_per_session_with_confidence_intervals_up_to_a_tenth_of_the_session() -> None:
    cols, _ = generate(20_005, causes=["warmup"])
    r = analyze(LogData(cols, {}, [], "w")).result
    fid = r["fidelity"]
    assert len(fid["sessions"]) == 3 and fid["ensemble"] >= 4
    s = fid["sessions"][0]
    assert s["tau_s"][0] == 0.04
    assert s["tau_s"][-1] <= s["samples"] / 25.0 / 10
    assert all(lo <= m <= hi for lo, m, hi in zip(s["ci_low"]["x"], s["measured"]["x"], s["ci_high"]["x"],
                                                 strict=True))


def test_temperature_and_its_rate_together_are_both_named_not_a_random_walk() -> None:
    cols, h = generate(11, causes=["temperature", "temperature_rate"])
    r = analyze(LogData(cols, {}, [], "pair")).result
    found = {f["cause"]: f["axes"] for f in r["findings"]}
    assert "random_walk" not in found
    assert found.get("temperature") == h.axes["temperature"]
    assert found.get("temperature_rate") == h.axes["temperature_rate"]


def test_noise_causes_map_onto_the_truth_model_so_sim_reproduces_the_allan_curve() -> None:
    """coloured_noise and bias_instability findings -> truth model (gm, flicker): the virtual unit's
    still output has the fitted model's Allan deviation, within 0.1 decade at every octave tau."""
    from gyrocal.analysis.extend import truth_from_result
    from gyrocal.analysis.noisemodel import octave_m, overlapping_avar
    from gyrocal.sim.schedule import still
    from gyrocal.sim.truth import SessionStream

    rate = 50.0
    m = NoiseModel(rate, 0.01**2, [(1 / rate, 0.012**2), (2 / rate, 0.008**2), (5.12, 0.002**2),
                                   (81.92, 0.0015**2)], 0.0)
    axes = ["x", "y", "z"]
    findings = [
        {"cause": "coloured_noise", "axes": axes, "params": {
            "gauss_markov": {a: [{"tau_s": t, "sd_dps": np.sqrt(v)} for t, v in m.fast] for a in axes},
            "white_dps": {a: np.sqrt(m.white_var) for a in axes}}},
        {"cause": "bias_instability", "axes": axes, "params": {
            "flicker_bank": {a: [{"tau_s": t, "sd_dps": np.sqrt(v)} for t, v in m.slow] for a in axes}}},
    ]
    truth = truth_from_result({"findings": findings, "noise_dps": {a: m.sample_sd for a in axes},
                               "samples": {"rate_hz": rate}})
    assert truth.noise_dps == 0.01 and np.all(truth.effects.gm_dps > 0)
    assert np.all(truth.effects.bias_instability_dps > 0)
    n = int(1200 * rate)
    w = SessionStream(truth, still(), rate, 3, 0).chunk(n)["wx"]
    mm = octave_m(n, 0.1).astype(float)
    dec = np.log10(np.sqrt(overlapping_avar(w, mm) / m.avar(mm)))
    assert np.max(np.abs(dec)) < 0.1, dec


def test_a_found_line_maps_onto_the_truth_model_and_the_virtual_unit_renders_it() -> None:
    """A coloured_noise finding with a 31.45 Hz line on z (sunsided) -> Effects.lines: the virtual
    unit's still z output has the model's Allan deviation (white + line) within 0.1 decade at every
    octave tau, x has none of it, and the stream is the same whatever the chunking."""
    from gyrocal.analysis.extend import truth_from_result
    from gyrocal.analysis.noisemodel import octave_m, overlapping_avar
    from gyrocal.sim.schedule import still
    from gyrocal.sim.truth import SessionStream

    rate = 100.0
    axes = ["x", "y", "z"]
    line = {"frequency_hz": 31.45, "half_width_hz": 0.13, "sd_dps": 0.06}
    findings = [{"cause": "coloured_noise", "axes": ["z"], "params": {
        "gauss_markov": {"z": []}, "white_dps": {"z": 0.09}, "lines": {"z": [line]}}}]
    truth = truth_from_result({"findings": findings, "noise_dps": {a: 0.09 for a in axes},
                               "samples": {"rate_hz": rate}})
    assert truth.effects.lines == [(2, 31.45, 0.13, 0.06)] and truth.effects.any()
    from gyrocal.errors import ConfigError
    from gyrocal.sim.truth import TruthModel, set_noise
    assert set_noise(TruthModel(), ["line_z=31.45,0.13,0.06"]).effects.lines == truth.effects.lines
    with pytest.raises(ConfigError, match="line_z"):
        set_noise(TruthModel(), ["line_z=31.45,0.13"])
    n = int(600 * rate)
    whole = SessionStream(truth, still(), rate, 3, 0).chunk(n)
    s = SessionStream(truth, still(), rate, 3, 0)
    parts = [s.chunk(k) for k in (1, 2, 997, n - 1000)]
    assert np.array_equal(np.concatenate([p["wz"] for p in parts]), whole["wz"])
    model = NoiseModel(rate, 0.09**2, [], 0.0, lines=[(31.45, 0.13, 0.06**2)])
    mm = octave_m(n, 0.1).astype(float)
    dec = np.log10(np.sqrt(overlapping_avar(whole["wz"], mm) / model.avar(mm)))
    assert np.max(np.abs(dec)) < 0.1, dec
    assert np.std(whole["wz"]) == pytest.approx(np.sqrt(0.09**2 + 0.06**2), rel=0.05)
    assert np.std(whole["wx"]) == pytest.approx(0.09, rel=0.05)


def test_a_wandering_line_is_narrow_band_noise_whose_allan_shape_matches_its_simulation() -> None:
    """A 31.4 Hz resonance of 0.06 deg/s (sunsided z): the line's Allan shape equals its simulated
    curve, and fitting it recovers its variance where white + colour alone misfit by thousands."""
    from gyrocal.analysis.noisemodel import octave_m, overlapping_avar

    rate = 100.0
    truth = NoiseModel(rate, 0.1**2, [], 0.0, lines=[(31.4, 0.05, 0.06**2)])
    x = truth.simulate(100_000, np.random.default_rng(1))
    mm = octave_m(x.size, 0.01).astype(float)  # up to 1000 samples: every octave has >= 100 clusters
    assert np.max(np.abs(np.log10(np.sqrt(overlapping_avar(x, mm) / truth.avar(mm))))) < 0.05
    with_line = fit_noise(x, rate, lines=((31.4, 0.05),))
    assert np.sqrt(with_line.lines[0][2]) == pytest.approx(0.06, rel=0.1)
    assert fit_noise(x, rate).misfit > 100 * max(with_line.misfit, 1.0)


def test_a_wandering_line_in_a_log_is_named_coloured_noise_with_its_frequency_not_periodic() -> None:
    """A 7.3 Hz resonance (half width 0.1 Hz, 1 sigma) on z of a null tumble log: the analysis
    models it as narrow-band noise (coloured_noise on z, its centre within 0.05 Hz), not a sinusoid."""
    cols, _ = generate(5, causes=[])
    line = NoiseModel(25.0, 0.0, [], 0.0, lines=[(7.3, 0.1, 0.002**2)])
    cols["wz"] = cols["wz"] + line.simulate(cols["t"].size, np.random.default_rng(5))
    res = analyze(LogData(cols, {}, [], "line")).result
    found = {f["cause"]: f for f in res["findings"]}
    assert not set(found) & REGRESSION
    assert found["coloured_noise"]["axes"] == ["z"]
    (f0, _, sd), = [(q["frequency_hz"], q["half_width_hz"], q["sd_dps"])
                    for q in found["coloured_noise"]["params"]["lines"]["z"]]
    assert f0 == pytest.approx(7.3, abs=0.05) and sd == pytest.approx(0.002, rel=0.3)
    assert res["fidelity"]["after"]["z"] < res["fidelity"]["without_colour"]["z"]


def test_gls_gram_by_one_segmented_sweep_equals_the_full_solve() -> None:
    """``gram`` sweeps U'^-1 once, in row segments coupled by the last d rows: the same x'V^-1x."""
    from gyrocal.analysis import gls

    m = NoiseModel(10.0, 0.01, [(0.1, 0.02), (2.0, 0.005), (20.0, 0.003)], 1e-4)
    t = np.arange(400) / 10.0
    t[200:] += 3.0
    sess = (np.arange(400) >= 300).astype(float)
    w = np.ones(400)
    w[10:15] = 0.0
    g = gls.StateSpaceGLS(m, t, sess, w)
    x = np.random.default_rng(2).normal(size=(400, 5))
    ref = x.T @ g.vinv(x)
    old = gls.SEGMENT_ROWS
    try:
        for seg in (7, 64, 1 << 18):  # 7 -> 6 rows: a segment boundary inside every other sample
            gls.SEGMENT_ROWS = seg
            assert np.allclose(g.gram(x), ref, rtol=1e-10, atol=1e-12)
    finally:
        gls.SEGMENT_ROWS = old


def test_a_broad_resonance_is_found_where_a_low_pass_and_white_noise_show_none() -> None:
    """A 5 Hz bump (half width 1 Hz, 2 sigma) on x of a null tumble log is found near 5 Hz with about
    its width; a first-order low-pass (y, the coloured background) and white noise (z) show no bump."""
    from gyrocal.analysis.baseline import build_problem, lstsq
    from gyrocal.analysis.resonance import find_resonance
    from gyrocal.analysis.segments import usable_samples
    from gyrocal.model.terms import derived_columns

    cols, _ = generate(5, causes=[])
    n, rng = cols["t"].size, np.random.default_rng(5)
    cols["wx"] = cols["wx"] + NoiseModel(25.0, 0.0, [], 0.0, lines=[(5.0, 1.0, 0.004**2)]).simulate(n, rng)
    cols["wy"] = cols["wy"] + NoiseModel(25.0, 0.0, [(0.08, 0.003**2)], 0.0).simulate(n, rng)
    c = derived_columns(cols)
    prob = build_problem(c, usable_samples(c))
    beta, _ = lstsq(prob.base, prob.y)
    x, y, z = find_resonance(prob, prob.y - prob.base @ beta)
    assert y == () and z == ()
    (f0, hw), = x
    assert f0 == pytest.approx(5.0, abs=0.4) and 0.5 <= hw <= 2.0


@pytest.mark.parametrize("seed, kind, cause, axis", [(30022, "flicker", "temperature", 0),
                                                      (30098, "flicker", "temperature_rate", 1)])
def test_a_covariate_does_not_take_a_flicker_nulls_wander_through_the_error_model(
        seed: int, kind: str, cause: str, axis: int) -> None:
    """Two feasible-GLS rounds let a once-per-session temperature rise take a 300 s flicker member
    and named it at p = 1e-5 / 4e-4 (the true error model gives 0.07 / 0.015); one round does not."""
    from gyrocal.analysis.baseline import build_problem
    from gyrocal.analysis.candidates import all_candidates
    from gyrocal.analysis.holdout import ALPHA
    from gyrocal.analysis.lrtest import build_axis_lr
    from gyrocal.analysis.segments import usable_samples
    from gyrocal.model.terms import derived_columns

    cols, _ = generate(seed, causes=[])
    c = derived_columns(add_background(cols, kind, seed))
    prob = build_problem(c, usable_samples(c))
    lr = build_axis_lr(prob, all_candidates(prob), axis)
    assert lr.test([], cause)[1] > ALPHA


def test_the_walk_is_not_named_on_a_quantised_white_null() -> None:
    """The walk's smoother with the test's upper-limit error model named random_walk on this
    quantised white-noise null (seed 30028, z, p = 7e-5); with the point-estimate model, nothing."""
    cols, _ = generate(30028, causes=[])
    res = analyze(LogData(add_background(cols, "quantised", 30028), {}, [], "q")).result
    assert res["findings"] == []


def test_sessions_whose_noise_differs_get_their_own_error_model_in_the_fidelity() -> None:
    """A null tumble log whose first session has 3x the white noise on x (a recording made on another
    day): the x sessions reject the pooled error model, each session is simulated under its own, and
    the fidelity on x stays well under the 0.2 decades a pooled model would miss session 0 by; y and
    z, whose sessions agree, keep the pooled model."""
    cols, _ = generate(7, causes=[], session_s=600.0)  # >= 1024 still samples per session
    first = cols["session"] == np.unique(cols["session"])[0]
    rng = np.random.default_rng(7)
    cols["wx"] = cols["wx"] + np.where(first, rng.normal(0.0, np.sqrt(8) * 0.002, cols["wx"].size), 0.0)
    fid = analyze(LogData(cols, {}, [], "sessions differ")).result["fidelity"]
    sm = fid["session_models"]
    assert sm["x"]["differ"] and not sm["y"]["differ"] and not sm["z"]["differ"], sm
    assert fid["own_models"] == len(fid["sessions"]) == 3
    assert all(set(row["own_model"]) == {"x"} for row in fid["sessions"])
    assert fid["after"]["x"] < 0.05
