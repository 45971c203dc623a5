"""The shared foundation: log format, term specs, truth model and schedule geometry."""

from pathlib import Path

import numpy as np
import pytest

from gyrocal.errors import ConfigError, LogFormatError
from gyrocal.logformat import read_log, write_log
from gyrocal.model.terms import SEED000_TERMS, TermSpec, derived_columns
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import SEED000_TABLE1_DPH, SessionStream, TruthModel


def test_log_round_trip_keeps_values_and_metadata(tmp_path: Path) -> None:
    cols = {k: np.linspace(0, 1, 5) for k in ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp")}
    write_log(tmp_path / "a.csv", cols, {"serial": "42"})
    log = read_log(tmp_path / "a.csv")
    assert log.metadata == {"serial": "42", "units": "gyro=deg/s accel=g temp=degC time=s"}
    np.testing.assert_allclose(log["temp"], cols["temp"])
    assert np.all(log["session"] == 0)


def test_log_nan_rows_are_skipped_and_reported(tmp_path: Path) -> None:
    p = tmp_path / "n.csv"
    p.write_text("t,wx,wy,wz,ax,ay,az\n0,1,2,3,0,0,1\n1,nan,2,3,0,0,1\n2,1,2,inf,0,0,1\n3,1,2,3,0,0,1\n")
    log = read_log(p)
    assert len(log) == 2 and log.skipped_rows == [3, 4]


@pytest.mark.parametrize(
    "body, needle",
    [
        ("t,wx,wy,wz,ax,ay\n0,1,2,3,0,0\n", "az"),
        ("t,wx,wy,wz,ax,ay,az\n0,1,2,x3,0,0,1\n", ":2: column 'wz'"),
        ("t,wx,wy,wz,ax,ay,az\n0,1,2,3,0,0\n", ":2: 6 fields"),
        ("t,wx,wy,wz,ax,ay,az\n1,1,2,3,0,0,1\n0,1,2,3,0,0,1\n", "goes backwards"),
    ],
)
def test_log_bad_file_error_names_line_and_column(tmp_path: Path, body: str, needle: str) -> None:
    p = tmp_path / "bad.csv"
    p.write_text(body)
    with pytest.raises(LogFormatError, match=needle.replace("(", r"\(")):
        read_log(p)


def test_terms_seed000_design_and_extensions() -> None:
    cols = {"ax": np.array([0.5]), "ay": np.array([-0.5]), "az": np.array([0.7]),
            "temp": np.array([30.0]), "t": np.array([1 / 8]), "t_on": np.array([100.0])}
    phi = TermSpec.parse(SEED000_TERMS).design(cols)[0]
    np.testing.assert_allclose(phi, [1, .5, -.5, .7, .25, .25, .49, -.25, -.35, .35])
    ext = TermSpec.parse(["temp^2", "exp(-t_on/100)", "sin(2)", "gx*temp"]).design(cols)[0]
    np.testing.assert_allclose(ext, [900, np.exp(-1), np.sin(2 * np.pi * 2 / 8), 15])
    with pytest.raises(ConfigError, match="not a column name"):
        TermSpec.parse(["gx+gy"])
    with pytest.raises(ConfigError, match="does not have"):
        TermSpec.parse(["humidity"]).design(cols)


def test_derived_temperature_rate_recovers_a_linear_ramp() -> None:
    t = np.arange(0, 100, 0.1)
    d = derived_columns({"t": t, "temp": 20 + 0.05 * t, "session": np.zeros_like(t)})
    np.testing.assert_allclose(d["dtemp"], 0.05, atol=1e-9)
    np.testing.assert_allclose(d["t_on"], t)


def test_truth_x_axis_is_seed000_table1_and_chunks_compose() -> None:
    m = TruthModel()
    np.testing.assert_allclose(m.coeffs_dps[0] * 3600, SEED000_TABLE1_DPH)
    a = SessionStream(m, tumble(), 200, seed=3, boot=1)
    b = SessionStream(m, tumble(), 200, seed=3, boot=1)
    whole = a.chunk(1000)
    parts = [b.chunk(n) for n in (1, 499, 500)]
    for k in ("wx", "az", "drift_wz"):
        np.testing.assert_array_equal(whole[k], np.concatenate([p[k] for p in parts]))
    assert not np.allclose(m.switch_on_bias(3, 1), m.switch_on_bias(3, 2))


def test_schedule_rates_match_gravity_motion() -> None:
    g, w, still = tumble(dwell_s=1.0, move_s=0.5).state(np.arange(0, 27, 1e-3))
    dg = np.gradient(g, 1e-3, axis=0)
    pred = -np.cross(np.radians(w), g)
    inner = ~still & np.roll(~still, 2) & np.roll(~still, -2)
    np.testing.assert_allclose(dg[inner], pred[inner], atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0)
