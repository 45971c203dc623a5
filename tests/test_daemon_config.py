"""Daemon configuration: the shipped files load, and every mistake names file, field and fix."""

from __future__ import annotations

from pathlib import Path
from typing import Any

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
        ("link: {url: /dev/x}\nestimator: {method: kalman}\n", ["estimator.method", "rls, nlms, lms or kf"]),
        ("link: {url: /dev/x}\npush: {retries: '3'}\n", ["push.retries", "'3'"]),
        ("link: {url: /dev/x}\nestimator: {terms: [gx, 'gx+gy']}\n", ["estimator.terms", "gx+gy"]),
        ("link: {url: /dev/x}\nvalidation: {min_improvement: 1.5}\n", ["validation.min_improvement"]),
        ("link: {url: /dev/x}\nfoo: 1\n", ["unknown field 'foo'"]),
        ("link: [1, 2\n", ["not valid YAML"]),
        ("link: {kind: serial}\n", ["link.url", "name the device"]),
        ("link: {url: ''}\n", ["link.url", "name the device"]),
        ("link: {url: /dev/x}\nvirtual_unit: {extra_args: [--nak-next, 1]}\n",
         ["virtual_unit.extra_args", "list of strings"]),
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
    # a Latin-1 degree sign in a comment: a traceback and a restart loop under systemd (an operator's audit)
    path.write_bytes(b"link:\n  url: auto  # 20 \xb0C lab\n")
    assert main(["run", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "line 2: byte 0xb0 is not UTF-8" in err[0] and "save the file as UTF-8" in err[0]


def test_run_with_an_unknown_port_starts_waiting_and_says_so_in_one_line(tmp_path: Path) -> None:
    # issue 8: the daemon starts without the unit (under systemd an exit would be a restart loop);
    # the missing port is named in one log line and in status (WAIT_UNIT), then it keeps trying
    import signal
    import subprocess
    import sys
    import time

    from gyrocal.daemon.control import request

    path = tmp_path / "c.yaml"
    sock = tmp_path / "c.sock"
    path.write_text(f"link: {{url: /dev/does-not-exist-42}}\nstate_dir: {tmp_path}/s\n"
                    f"control_socket: {sock}\n")
    log = tmp_path / "daemon.log"
    with log.open("w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "gyrocal.cli", "run", "--config", str(path)],
                                stdout=out, stderr=subprocess.STDOUT)
    try:
        st: dict = {}
        end = time.monotonic() + 60
        while time.monotonic() < end and st.get("state") != "WAIT_UNIT":
            time.sleep(0.2)
            try:
                st = request(sock, {"cmd": "status"}, timeout=5.0)
            except Exception:
                st = {}
        assert st.get("state") == "WAIT_UNIT" and "/dev/does-not-exist-42" in st["reason"], st
        time.sleep(2.5)  # several reconnect rounds: still one line
        lines = [ln for ln in log.read_text().splitlines()
                 if "does-not-exist-42" in ln and "cannot be opened" in ln and "WARNING" in ln]
        assert len(lines) == 1, lines  # (the WAIT_UNIT state line, INFO, carries the cause as status does)
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0


# --- ranges: every numeric field, at start and at SIGHUP reload -----------------------------------

from gyrocal.daemon.config import _RANGES, _SCHEMA  # noqa: E402

_BAD_VALUES: dict[str, list[object]] = {
    "link.baudrate": [0, -9600, 10**9],
    "link.reconnect_max_s": [0, -1, 1e9, float("nan")],
    "virtual_unit.seed": [-1],
    "virtual_unit.rate_hz": [0, 5000],
    "virtual_unit.dwell_s": [0, -1.2],
    "virtual_unit.move_s": [0, -0.4],
    "estimator.forgetting": [0.5, 1.01, float("nan")],
    "estimator.step": [0, 2, -0.1],
    "validation.holdout_every": [1, 0],
    "validation.block_s": [0, -0.5, 0.001, float("inf")],
    "validation.min_improvement": [1, -0.1],
    "validation.min_holdout_blocks": [0],
    "push.ack_timeout_s": [0, -1, float("nan")],
    "push.retries": [0, -3],
    "monitor.alarm_ratio": [1, 0.5],
    "monitor.window_s": [0, -10],
    "monitor.alarm_floor_dps": [-0.001],
    "still.window_s": [0, -0.2],
    "still.gyro_std_dps": [0, -0.05],
    "still.accel_tol_g": [0, 2],
    "still.k_std": [1, 0.5],
    "still.k_turn": [1, 0.5],
    "still.margin_s": [-0.1],
    "still.min_run_s": [0, -1],
    "still.learn_s": [0],
    "still.memory_s": [0],
    "link.can_node_id": [-1, 16],
    "push.target_drift_dph": [0, -1],
    "push.min_cut": [1, 0.5],
    "push.wander_horizon_s": [0, -600],
    "store.keep_versions": [-1],
    "site.latitude_deg": [-91, 90.5, float("nan")],
}


def test_every_numeric_field_has_a_range_and_a_bad_value_here() -> None:
    numeric = {f"{sec}.{fld}" for sec, fields in _SCHEMA.items() for fld, spec in fields.items()
               if int in spec[0] or float in spec[0]}
    assert numeric == set(_RANGES), "a numeric config field without a range (add it to _RANGES)"
    assert numeric == set(_BAD_VALUES), "a numeric config field without a bad value in this test"


def _write(tmp_path: Path, dotted: str, value: object) -> Path:
    import yaml

    section, fld = dotted.split(".")
    doc = {"link": {"url": "/dev/x"}, section: {fld: value}}
    if section == "link":
        doc["link"]["url"] = "/dev/x"
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize(("dotted", "value"), [(k, v) for k, vs in _BAD_VALUES.items() for v in vs])
def test_every_field_with_a_bad_value_is_refused_with_its_name(tmp_path: Path, dotted: str,
                                                               value: object) -> None:
    path = _write(tmp_path, dotted, value)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    text = str(err.value)
    assert str(path) in text and f"field '{dotted}'" in text and "outside" in text and "\n" not in text


@pytest.mark.parametrize(("dotted", "value"), [("validation.block_s", 0.02), ("push.ack_timeout_s", 0.05),
                                               ("estimator.forgetting", 1), ("monitor.alarm_floor_dps", 0)])
def test_values_inside_the_ranges_load(tmp_path: Path, dotted: str, value: object) -> None:
    section, fld = dotted.split(".")
    assert getattr(load_config(_write(tmp_path, dotted, value)), section)[fld] == value


def test_cross_field_and_convergence_ranges(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("link: {url: /dev/x}\nvalidation: {block_s: 2}\nmonitor: {window_s: 1}\n")
    with pytest.raises(ConfigError, match=r"field 'monitor.window_s' is 1; write a window >= validation"):
        load_config(path)
    path.write_text("link: {url: /dev/x}\nestimator: {convergence: {window: 0}}\n")
    with pytest.raises(ConfigError,
                       match=r"c.yaml: field 'estimator.convergence.window' is 0; write a number > 0"):
        load_config(path)


def _reload_only_engine(path: Path) -> Any:
    """An Engine with just what its SIGHUP reload path uses: the config from ``path`` and a notifier."""
    from gyrocal.daemon.engine import Engine

    class _Notifier:
        def reloading(self) -> None: ...
        def ready(self) -> None: ...

    eng = Engine.__new__(Engine)  # only the reload path: no link, no store
    eng.cfg = load_config(path)
    eng.notifier = _Notifier()
    return eng


def test_the_sighup_reload_refuses_a_bad_range_and_keeps_the_old_config(tmp_path: Path, caplog) -> None:
    """The engine's reload path (load_config on SIGHUP): a refused reload keeps the config, one line."""
    path = tmp_path / "c.yaml"
    path.write_text("link: {url: /dev/x}\nvalidation: {block_s: 0.5}\n")
    eng = _reload_only_engine(path)
    path.write_text("link: {url: /dev/x}\nvalidation: {block_s: 0}\npush: {ack_timeout_s: -1}\n")
    with caplog.at_level("ERROR"):
        eng._reload()
    assert eng.cfg.validation["block_s"] == 0.5 and eng.cfg.push["ack_timeout_s"] == 1.0
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "validation.block_s" in errors[0] and str(path) in errors[0]
    assert eng.last_reload["ok"] is False and "validation.block_s" in eng.last_reload["error"]  # status


def test_a_reload_says_what_waits_for_a_restart_or_a_switch_on(tmp_path: Path, caplog) -> None:
    """state_dir and friends were ignored without a word; still and site wait for the next session."""
    path = tmp_path / "c.yaml"
    path.write_text(f"link: {{url: /dev/x}}\nstate_dir: {tmp_path / 'a'}\n")
    eng = _reload_only_engine(path)
    path.write_text(f"link: {{url: /dev/y}}\nstate_dir: {tmp_path / 'b'}\nstill: {{k_std: 5}}\n"
                    "site: {latitude_deg: 48.1}\n")
    with caplog.at_level("INFO"):
        eng._reload()
    said = " | ".join(r.getMessage() for r in caplog.records)
    assert "state_dir changed" in said and "next restart" in said
    assert "link.url '/dev/x' -> '/dev/y'" in said  # named, as every other field (it said "link settings")
    assert "still.k_std 4.0 -> 5" in said and "site.latitude_deg default -> 48.1" in said, said
    assert "next switch-on" in said
    assert eng.cfg.site["latitude_deg"] == 48.1 and eng.last_reload["ok"]


def test_a_reload_names_every_field_it_changed_and_when_it_takes_effect(tmp_path: Path, caplog) -> None:
    """estimator.method, push.retries and store.keep_versions changed with nothing in the log but
    "configuration reloaded" (an operator's audit)."""
    path = tmp_path / "c.yaml"
    path.write_text("link: {url: /dev/x}\n")
    eng = _reload_only_engine(path)
    path.write_text("link: {url: /dev/x}\nestimator: {method: kf, convergence: {window: 3000}}\n"
                    "push: {retries: 5}\nstore: {keep_versions: 3}\nvalidation: {block_s: 0.25}\n")
    with caplog.at_level("INFO"):
        eng._reload()
    said = {r.getMessage().split(":")[1].strip(): r.getMessage() for r in caplog.records
            if r.getMessage().startswith("SIGHUP: changed")}
    assert len(said) == 2 and "changed, in effect now" in said
    now, later = said["changed, in effect now"], said[next(k for k in said if "next" in k)]
    assert "push.retries 3 -> 5" in now and "store.keep_versions 1000 -> 3" in now and "block_s" not in now
    assert "estimator.method 'rls' -> 'kf'" in later
    assert "estimator.convergence.window default -> 3000" in later
    assert "validation.block_s 0.5 -> 0.25" in later and eng.cfg.push["retries"] == 5


def test_the_sighup_reload_takes_new_terms_for_the_next_session(tmp_path: Path, caplog) -> None:
    """Before, a reload replaced the estimator section but not the resolved term list the learner is
    built from, so new terms were silently ignored until a restart."""
    path = tmp_path / "c.yaml"
    path.write_text("link: {url: /dev/x}\n")
    eng = _reload_only_engine(path)
    names = ["1", "gx", "gy", "gz", "temp", "dtemp"]
    path.write_text(f"link: {{url: /dev/x}}\nestimator: {{terms: {names!r}}}\n")
    with caplog.at_level("INFO"):
        eng._reload()
    assert eng.cfg.terms == names
    assert any("next switch-on" in r.getMessage() for r in caplog.records)


# --- CAN: python-can's own configuration fills what link.can leaves out ---------------------------------

@pytest.fixture
def no_can_env(tmp_path: Path, monkeypatch) -> Path:
    for var in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # ~/.canrc is read from here
    return tmp_path


def test_can_link_takes_interface_and_channel_from_the_environment(no_can_env: Path, monkeypatch) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "gyro")
    path = no_can_env / "c.yaml"
    path.write_text("link: {kind: can}\n")
    assert load_config(path).link["can"] == {"interface": "virtual", "channel": "gyro"}
    path.write_text("link: {kind: can, can: {channel: other}}\n")  # the config file wins
    assert load_config(path).link["can"] == {"interface": "virtual", "channel": "other"}


def test_can_link_takes_its_defaults_from_canrc(no_can_env: Path) -> None:
    (no_can_env / ".canrc").write_text("[default]\ninterface = socketcan\nchannel = vcan0\n"
                                       "bitrate = 500000\n")
    path = no_can_env / "c.yaml"
    path.write_text("link: {kind: can}\n")
    assert load_config(path).link["can"] == {"interface": "socketcan", "channel": "vcan0", "bitrate": 500000}


def test_can_link_without_any_interface_names_the_field_and_python_cans_config(no_can_env: Path,
                                                                                  monkeypatch) -> None:
    path = no_can_env / "c.yaml"
    path.write_text("link: {kind: can}\n")
    with pytest.raises(ConfigError, match=r"field 'link.can' .*CAN_INTERFACE"):
        load_config(path)
    monkeypatch.setenv("CAN_INTERFACE", "no_such_bus")
    with pytest.raises(ConfigError, match=r"c.yaml: field 'link.can'.*unknown interface"):
        load_config(path)


def test_terms_a_unit_cannot_evaluate_are_refused_and_new_sets_are_registered(tmp_path: Path) -> None:
    """A column the analysis may fit but no sample carries ('temperature', a typo for temp) would fail
    every block at run time: refused at load, naming the file, the field and the atoms to use. A set of
    unit atoms outside the protocol's built-in table is registered, so that the daemon pushes it and
    the unit answers for itself (ACK, or NAK UNKNOWN_TERMS: tests/test_daemon_e2e.py)."""
    from gyrocal.protocol import termsets

    path = tmp_path / "c.yaml"
    path.write_text("link: {url: /dev/x}\nestimator: {terms: ['1', gx, 'temperature^2']}\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    text = str(err.value)
    assert str(path) in text and "field 'estimator.terms'" in text and "'temperature'" in text
    assert "temp, dtemp, t_on" in text
    names = ["1", "gx", "gy", "gz", "temp*dtemp", "exp(-t_on/250)"]
    assert termsets.names_for(termsets.terms_id(names)) is None
    path.write_text(f"link: {{url: /dev/x}}\nestimator: {{terms: {names!r}}}\n")
    assert load_config(path).terms == names
    assert termsets.names_for(termsets.terms_id(names)) == tuple(names)


def test_a_field_given_twice_is_refused_with_its_line(tmp_path: Path) -> None:
    """PyYAML keeps the last of two equal keys silently: a second `push:` would undo the first."""
    path = tmp_path / "c.yaml"
    path.write_text("link: {url: /dev/x}\npush: {retries: 5}\nmonitor: {window_s: 10}\npush: {retries: 2}\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert f"{path}:4" in str(err.value) and "'push' appears twice; keep one" in str(err.value)
    path.write_text("link: {url: /dev/x, url: /dev/y}\n")
    with pytest.raises(ConfigError, match="'url' appears twice"):
        load_config(path)


def test_an_empty_config_file_says_it_is_empty(tmp_path: Path) -> None:
    """An empty file (a botched edit) was refused as "field 'link.url' is 'auto'": an operator's soak."""
    path = tmp_path / "empty.yaml"
    path.write_text("# nothing here\n")
    with pytest.raises(ConfigError, match="the file is empty"):
        load_config(path)
