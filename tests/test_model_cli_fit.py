"""``gyrocal fit`` prints Contract 3 JSON; terms from --terms or a YAML terms file; user errors exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gyrocal.cli import main
from gyrocal.errors import ConfigError
from gyrocal.logformat import write_log
from gyrocal.model.convergence import ConvergenceConfig
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import SessionStream, TruthModel


@pytest.fixture(scope="module")
def log_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cols = SessionStream(TruthModel(), tumble(), 100.0, seed=2, boot=0).chunk(7200)
    path = tmp_path_factory.mktemp("fit") / "sim.csv"
    write_log(path, {k: cols[k] for k in ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session")},
              {"serial": "sim"})
    return path


@pytest.mark.parametrize("method", ["lms", "nlms", "rls", "batch"])
def test_fit_json_has_the_contract_3_shape(
    log_path: Path, method: str, capsys: pytest.CaptureFixture
) -> None:
    assert main(["fit", str(log_path), "--method", method, "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert {"method", "terms", "samples", "coefficients", "uncertainty", "identifiable", "rms"} <= set(res)
    assert res["method"] == method and len(res["terms"]) == 10 and 3000 < res["samples"] < 7200
    for key in ("coefficients", "uncertainty"):
        assert set(res[key]) == {"x", "y", "z"} and all(len(v) == 10 for v in res[key].values())
    assert res["identifiable"]["rank"] == 9
    assert res["identifiable"]["undetermined"] == ["1 - gx^2 - gy^2 - gz^2"]
    assert res["uncertainty"]["x"][0] is None and res["uncertainty"]["x"][1] > 0
    assert all(0 < res["rms"][a] < 0.01 for a in "xyz")


def test_fit_takes_a_terms_file_and_extra_terms(log_path: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture) -> None:
    spec = tmp_path / "ext.yaml"
    spec.write_text("terms: ['1', gx, gy, gz, temp, temp*dtemp]\n")
    assert main(["fit", str(log_path), "--terms-file", str(spec), "--json", "--all-samples"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["terms"] == ["1", "gx", "gy", "gz", "temp", "temp*dtemp"] and res["samples"] == 7200
    # the range the set was fitted over (push --file writes it as an autopilot's TMIN..TMAX)
    temps = np.loadtxt(log_path, delimiter=",", skiprows=3, usecols=7)
    assert res["temp_range_c"] == pytest.approx([temps.min(), temps.max()], abs=1e-6)
    assert main(["fit", str(log_path), "--terms", "1", "gx", "gy", "gz"]) == 0
    assert "rank 4 of 4" in capsys.readouterr().out


def test_fit_user_errors_exit_2_with_one_line(log_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["fit", str(log_path), "--terms", "1", "pressure"]) == 2
    assert "pressure" in capsys.readouterr().err


def test_convergence_config_from_dict_names_file_field_and_fix() -> None:
    cfg = ConvergenceConfig.from_dict({"window": 500, "max_sigma_dps": 1e-4}, source="d.yaml")
    assert cfg.window == 500 and cfg.max_sigma_dps == 1e-4 and cfg.min_rank == ConvergenceConfig().min_rank
    with pytest.raises(ConfigError, match=r"d.yaml: field 'convergence.windw' is unknown; use one of window"):
        ConvergenceConfig.from_dict({"windw": 5}, source="d.yaml")
    with pytest.raises(ConfigError, match=r"field 'convergence.window' is 'x', not an integer"):
        ConvergenceConfig.from_dict({"window": "x"}, source="d.yaml")
    with pytest.raises(ConfigError, match=r"'convergence.max_error_ratio' is -1; write a number > 0"):
        ConvergenceConfig.from_dict({"max_error_ratio": -1}, source="d.yaml")
    assert np.isfinite(ConvergenceConfig.from_dict(None).max_change_dps)


def test_fit_of_a_unit_that_held_a_set_adds_it_back(tmp_path: Path) -> None:
    """A recording's unit held v3: its gyro columns are compensated with it (logformat.md, section 1).
    `fit` fitted them as they were, i.e. what is left after v3, with no word, and `push --file` of
    that output would have replaced v3 by its remainder (an audit with foreign recordings). It now adds
    v3 back, says so, and fits the whole drift: the same log without the applied_* lines fits v3 less."""
    from gyrocal.model.cli_fit import fit
    from gyrocal.readers import read_any
    from gyrocal.replay.source import applied_from_metadata

    src = Path(__file__).resolve().parents[1] / "data" / "sim_can" / "virtual_unit.blf"
    terms = ["1", "gx", "gy", "gz", "gx^2", "gy^2", "gz^2", "gx*gy", "gy*gz", "gx*gz"]  # v3's own
    with_set = fit(str(src), "batch", terms)
    log = read_any(str(src), None, None)
    held = applied_from_metadata(log.metadata, str(src))
    assert held is not None and held.version == 3
    assert with_set["applied_added"]["version"] == 3 and "added back" in with_set["warnings"][-1]
    plain = tmp_path / "plain.csv"
    write_log(plain, log.columns, {k: v for k, v in log.metadata.items() if not k.startswith("applied_")})
    bare = fit(str(plain), "batch", terms)
    assert "applied_added" not in bare
    got = np.array([np.subtract(with_set["coefficients"][a], bare["coefficients"][a]) for a in "xyz"])
    assert np.allclose(got, np.asarray(held.coeffs_dps), atol=1e-9)  # least squares is linear in y


def test_a_log_of_one_or_two_rows_is_not_fitted_as_still(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture) -> None:
    """1-2 rows were taken as a still period and "fitted" with numpy warnings, while 4-49 rows were
    refused (a foreign-log audit): too short to judge is not still, with the same one-line error."""
    n = 2
    cols = {"t": np.arange(n) * 0.01, "wx": np.zeros(n), "wy": np.zeros(n), "wz": np.zeros(n),
            "ax": np.zeros(n), "ay": np.zeros(n), "az": np.ones(n), "temp": np.full(n, 25.0)}
    f = tmp_path / "two.csv"
    write_log(f, cols)
    assert main(["fit", str(f)]) == 2
    assert "none of its 2 rows lies in a still period" in capsys.readouterr().err
