"""Daemon configuration: the shipped files load, and every mistake names file, field and fix."""

from __future__ import annotations

from pathlib import Path

import pytest

from gyrocal.cli import main
from gyrocal.daemon.config import load_config
from gyrocal.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent


def test_default_and_example_configs_load() -> None:
    d = load_config(None)
    assert d.virtual_unit["enabled"] and d.link["kind"] == "serial" and len(d.terms) == 10
    e = load_config(ROOT / "configs" / "gyrocal.example.yaml")
    assert not e.virtual_unit["enabled"] and e.link["url"] == "/dev/gyrocal-imu"
    assert e.estimator["convergence"]["max_sigma_dps"] == 0.001


@pytest.mark.parametrize(
    "body, needles",
    [
        ("link: {kind: serial, url: /dev/x, baud: 9600}\n", ["link.baud", "takes kind, url, baudrate"]),
        ("link: {kind: usb, url: /dev/x}\n", ["link.kind", "write `serial` or `can`"]),
        ("link: {url: /dev/x}\nestimator: {method: kalman}\n", ["estimator.method", "rls, nlms or lms"]),
        ("link: {url: /dev/x}\npush: {retries: '3'}\n", ["push.retries", "'3'"]),
        ("link: {url: /dev/x}\nestimator: {terms: [gx, 'gx+gy']}\n", ["estimator.terms", "gx+gy"]),
        ("link: {url: /dev/x}\nvalidation: {min_improvement: 1.5}\n", ["validation.min_improvement"]),
        ("link: {url: /dev/x}\nfoo: 1\n", ["unknown field 'foo'"]),
        ("link: [1, 2\n", ["not valid YAML"]),
        ("link: {kind: serial}\n", ["link.url", "name the device"]),
    ],
)
def test_broken_config_names_file_field_and_fix(tmp_path: Path, body: str, needles: list[str]) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(body)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    text = str(err.value)
    assert str(path) in text and "\n" not in text
    for n in needles:
        assert n in text


def test_run_with_a_broken_config_prints_one_line_and_exits_2(tmp_path: Path, capsys) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("estimator: {method: kalman}\nlink: {url: /dev/x}\n")
    assert main(["run", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "estimator.method" in err[0]
    assert main(["run", "--config", str(tmp_path / "missing.yaml")]) == 2
    assert "no such config file" in capsys.readouterr().err


def test_run_with_an_unknown_port_says_so_in_one_line(tmp_path: Path, capsys) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(f"link: {{url: /dev/does-not-exist-42}}\nstate_dir: {tmp_path}/s\n"
                    f"control_socket: {tmp_path}/c.sock\n")
    assert main(["run", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "/dev/does-not-exist-42" in err[-1]
