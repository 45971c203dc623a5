"""The Earth's rotation: in the virtual unit's truth (a real unit at rest reads it as true rate), and
found and removed by the daemon when it knows its latitude (gyrocal/daemon/earth_track.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from gyrocal.daemon.earth_track import EarthTrack
from gyrocal.model.earth import OMEGA_IE_DPS, earth_rate_body_dps, north_in_body, vertical_earth_rate_dps
from gyrocal.sim.grades import grade_truth
from gyrocal.sim.schedule import EarthFixed, tumble
from gyrocal.sim.truth import SessionStream
from tests.grade_harness import GradeRun

DPH = 3600.0


def test_a_vector_fixed_on_the_earth_turns_with_the_tumble_as_gravity_does() -> None:
    s = tumble(1.2, 0.4)
    t = np.arange(0.0, 3 * s.cycle_s, 0.011)
    g, _, _ = s.state(t)
    np.testing.assert_allclose(EarthFixed(s, s.poses_g[0]).at(t), g, atol=1e-12)


def test_the_earth_rate_at_rest_has_its_length_and_its_vertical_part() -> None:
    up = np.array([0.3, -0.2, 0.9])
    up /= np.linalg.norm(up)
    north = north_in_body(up, 37.0)
    assert abs(north @ up) < 1e-12 and abs(np.linalg.norm(north) - 1) < 1e-12
    e = earth_rate_body_dps(up, north, 52.0)
    assert np.linalg.norm(e) * DPH == pytest.approx(15.041, abs=1e-3)
    assert e @ up == pytest.approx(OMEGA_IE_DPS * np.sin(np.radians(52.0)))
    np.testing.assert_allclose(vertical_earth_rate_dps(2.0 * up[None, :], 52.0)[0], up * (e @ up))
    # heading 90: x points east, so north is where x was before turning 90 deg to the left
    x_east = north_in_body(np.array([0.0, 0.0, 1.0]), 90.0)
    np.testing.assert_allclose(x_east, [0.0, 1.0, 0.0], atol=1e-12)


def test_the_virtual_unit_reads_the_earth_rate_as_true_rate_not_drift() -> None:
    truth = dataclasses.replace(grade_truth("fibre", 200.0), latitude_deg=45.0, heading_deg=30.0)
    still = SessionStream(truth, tumble(1.2, 0.4), 200.0, 1, 1).chunk(200)  # the first rest, 1 s
    ref = np.column_stack([still[f"ref_w{a}"] for a in "xyz"])
    assert np.allclose(np.linalg.norm(ref, axis=1) * DPH, 15.041, atol=1e-3)
    flat_earth = dataclasses.replace(truth, latitude_deg=None)
    flat = SessionStream(flat_earth, tumble(1.2, 0.4), 200.0, 1, 1).chunk(200)
    for a in "xyz":  # the drift is the same with and without the turning Earth
        np.testing.assert_array_equal(still[f"drift_w{a}"], flat[f"drift_w{a}"])


def test_north_is_found_from_a_tumble_within_its_stated_sigma() -> None:
    """EarthTrack alone on the fibre unit's samples: integrated through the moves, fitted with the drift."""
    from gyrocal.model.prep import block_terms
    from gyrocal.model.terms import SEED000_TERMS, TermSpec

    lat, heading = 40.0, 120.0
    truth = dataclasses.replace(grade_truth("fibre", 400.0), latitude_deg=lat, heading_deg=heading)
    sched = tumble(1.2, 0.4)
    stream = SessionStream(truth, sched, 400.0, 2, 1)
    track = EarthTrack(lat, 10)
    spec = TermSpec.parse(SEED000_TERMS)
    seq0 = 0
    for _ in range(60):  # 60 s, 2.5 tumbles
        c = stream.chunk(400)
        n = c["t"].size
        w = np.column_stack([c[f"w{a}"] for a in "xyz"])
        a = np.column_stack([c[f"a{a}"] for a in "xyz"])
        still = c["still"].astype(bool)
        cref = track.advance(np.arange(seq0, seq0 + n), c["t"], w, a, still)
        seq0 += n
        phi = block_terms(spec, {"ax": a[:, 0], "ay": a[:, 1], "az": a[:, 2]})
        y = w - vertical_earth_rate_dps(a, lat)
        track.add(phi[still], y[still], cref[still])
        if track.fit(9):
            break
    assert track.known and track.references == 1
    up0 = sched.poses_g[0]
    true_h = earth_rate_body_dps(up0, north_in_body(up0, heading), lat) - vertical_earth_rate_dps(
        up0[None, :], lat)[0]
    cos_err = track.h @ true_h / (np.linalg.norm(track.h) * np.linalg.norm(true_h))
    err_deg = np.degrees(np.arccos(np.clip(cos_err, -1, 1)))
    assert err_deg < 3 * track.heading_sigma_deg + 0.5, (err_deg, track.heading_sigma_deg)
    assert 0.8 < track.fit_magnitude < 1.2


@pytest.mark.parametrize("heading", [0.0, 120.0])
def test_a_unit_that_turns_with_the_earth_is_calibrated_once_the_daemon_knows_its_latitude(
        tmp_path: Path, heading: float) -> None:
    """The demo unit at 45 deg N: without site.latitude_deg nothing is pushed in 100 s (the part of
    the Earth's rotation along north follows no gravity term, and the gate sees it); with it, north is
    found, the set is pushed and cuts every axis at least 10x, and the set holds no Earth rotation."""
    truth = dataclasses.replace(grade_truth("demo", 400.0), latitude_deg=45.0, heading_deg=heading)
    blind = GradeRun.make(tmp_path / "blind", "demo", 400.0, 1, truth=truth)
    blind.switch_on()
    blind.run(100, until=lambda r: bool(r.pushes))
    assert not blind.pushes
    told = GradeRun.make(tmp_path / "told", "demo", 400.0, 1, truth=truth, **{"site.latitude_deg": 45.0})
    told.switch_on()
    told.run(150, until=lambda r: any(p["push"].get("status") == "acked" for p in r.pushes))
    assert told.pushes and told.pushes[-1]["push"]["status"] == "acked"
    st = told.session.status()
    assert st["earth"]["north_found"] and st["earth"]["references"] == 1
    u = told.unit.status()
    for a in "xyz":
        assert u["drift_rms_compensated_dps"][a] * 10 <= u["drift_rms_raw_dps"][a], (a, u)


def test_a_link_that_loses_bursts_loses_the_frame_and_north_is_found_again(tmp_path: Path) -> None:
    """0.2 s lost in every 5 s: a gap during a move loses the frame the gyro integration carries. Each
    new frame's north comes from the joint fit with the drift already known (a rest or two), its
    samples teach nothing meanwhile, and the unit is still pushed and cut 10x."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_late_start import _lose_bursts

    truth = dataclasses.replace(grade_truth("demo", 400.0), latitude_deg=45.0, heading_deg=30.0)
    run = GradeRun.make(tmp_path, "demo", 400.0, 1, truth=truth, **{"site.latitude_deg": 45.0})
    run.switch_on()
    _lose_bursts(run, 0.2, 5.0, 150.0, until=lambda r: any(p["push"].get("status") == "acked"
                                                             for p in r.pushes))
    earth = run.session.status()["earth"]
    assert earth["references"] >= 2 and earth["last_loss"], earth  # the case is exercised
    assert any(p["push"].get("status") == "acked" for p in run.pushes)
    u = run.unit.status()
    for a in "xyz":
        assert u["drift_rms_compensated_dps"][a] * 10 <= u["drift_rms_raw_dps"][a], (a, u)
