"""``gyrocal sim`` as a command: one-line errors, recording, determinism, status file, signals."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gyrocal.cli import main as cli_main
from gyrocal.logformat import read_log
from tests.sim_helpers import SIM_CMD, SimProcess, read_status, wait_for


def _run(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([*SIM_CMD, *args], capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--schedule", "/nonexistent/poses.yaml"], "cannot read the schedule"),
        (["--rate", "0"], "--rate"),
        (["--garbage-rate", "2"], "--garbage-rate"),
        (["--latitude", "95"], "-90 to 90"),
        (["--link", "mavlink", "--latitude", "45"], "autopilot's Earth does not turn"),
        (["--lose-burst", "0.2"], "--lose-every"),
        (["--effect", "warmup_tau_s=0"], "one finite number > 0"),
        (["--effect", "warm=1"], "NAME one of"),
        (["--terms", "1,gx,zz"], "not an atom a unit evaluates"),
        (["--lose-burst", "0.2", "--lose-every", "0.1"], "longer than the burst"),
        (["--link", "can", "--can-config", "{not json"], "not valid JSON"),
        (["--link", "can", "--can-config", '{"interface": "no_such_bus"}'], "not a python-can interface"),
        (["--link", "can", "--can-config", '{"interface": "udp_multicast", "channel": "nope"}'],
         "cannot be opened"),
        (["--pty-link", "/nonexistent-dir/gyro0"], "--pty-link"),
        (["--flash", "/etc"], "--flash"),
        (["--ambient", "20,warm"], "--ambient"),
        (["--rise", "-1"], "--rise"),
        (["--warmup-tau", "0"], "--warmup-tau"),
    ],
)
def test_sim_broken_config_gives_one_line_error_and_exit_2(
    capsys: pytest.CaptureFixture[str], args: list[str], needle: str
) -> None:
    assert cli_main(["sim", *args]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gyrocal: error:") and needle in lines[0]


def test_sim_bad_schedule_contents_one_line_and_no_traceback_from_the_command(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("poses: [[0, 0]]\n")
    r = _run("--schedule", str(bad))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "poses" in r.stderr
    assert "Traceback" not in r.stderr


def _record_all(tmp_path: Path, runs: dict[str, tuple[str, ...]]) -> list[Path]:
    """Run several recording sims at once (they are independent processes)."""
    procs = []
    for name, extra in runs.items():
        cmd = [*SIM_CMD, "--rate", "200", "--duration", "1", "--record", str(tmp_path / name), *extra]
        procs.append(subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
    for p in procs:
        _, err = p.communicate(timeout=60)
        assert p.returncode == 0, err
    return [tmp_path / name for name in runs]


def test_sim_record_writes_contract1_log_and_truth_and_is_deterministic(tmp_path: Path) -> None:
    a, b, c = _record_all(tmp_path, {"a.csv": ("--seed", "5", "--power-cycle-every", "0.6"),
                                     "b.csv": ("--seed", "5", "--power-cycle-every", "0.6"),
                                     "c.csv": ("--seed", "6", "--power-cycle-every", "0.6")})
    log = read_log(a)
    assert len(log) == 200  # --duration counts samples: exactly 1 s worth at 200 Hz
    assert log.metadata["seed"] == "5" and log.metadata["serial"] == "4242"
    assert sorted(set(log["session"].tolist())) == [1.0, 2.0]  # session = boot counter
    first = log["session"] == 1
    np.testing.assert_allclose(log["t"][first], np.arange(first.sum()) / 200.0)
    truth_path = a.with_name("a.truth.csv")
    meta_lines = sum(1 for line in truth_path.read_text().splitlines() if line.startswith("#"))
    truth = np.genfromtxt(truth_path, delimiter=",", names=True, skip_header=meta_lines)
    assert len(truth) == 200 and {"drift_wx", "comp_wz", "ref_wy", "gz", "still"} <= set(truth.dtype.names)
    # no set applied: what was sent is reference rate + drift + white noise
    resid = log["wx"] - truth["ref_wx"] - truth["drift_wx"]
    assert abs(resid.mean()) < 1e-3 and resid.std() < 5e-3
    assert a.read_text() == b.read_text()
    assert a.read_text() != c.read_text()


def test_sim_temperature_course_per_switch_on_on_the_serial_unit(tmp_path: Path) -> None:
    """--ambient, --rise and --warmup-tau shape the unit's temperature, one ambient per switch-on (an
    outside check found them silently ignored off MAVLink: every switch-on warmed 25 -> 33 degC alike,
    so temperature, its rate and a warm-up could not be told apart in a recording)."""
    (a,) = _record_all(tmp_path, {"t.csv": ("--power-cycle-every", "0.5", "--ambient", "20,35", "--rise",
                                           "10", "--warmup-tau", "0.2")})
    log = read_log(a)
    first, second = log["temp"][log["session"] == 1], log["temp"][log["session"] == 2]
    assert 20.0 <= first.min() < 21.0 and 29.0 < first.max() < 30.0
    assert 35.0 <= second.min() < 36.0 and 44.0 < second.max() < 45.0


def test_sim_status_json_symlink_and_sigterm_exit_cleanly(tmp_path: Path) -> None:
    status, link = tmp_path / "st.json", tmp_path / "gyro0"
    sim = SimProcess("--rate", "100", "--status-json", str(status), "--pty-link", str(link),
                     tmp_path=tmp_path)
    try:
        assert os.readlink(link) == sim.address
        assert wait_for(lambda: read_status(status).get("samples_sent", 0) > 0)
        doc = read_status(status)
        assert doc["running"] is True and doc["boot_count"] == 1 and doc["link"] == "pty"
        assert set(doc["drift_rms_raw_dps"]) == {"x", "y", "z"} and doc["applied_version"] is None
        sim.power_cycle()
        assert wait_for(lambda: read_status(status).get("boot_count") == 2)
    finally:
        rc = sim.stop()
    assert rc == 0
    assert read_status(status)["running"] is False and not link.exists()
    assert not list(tmp_path.glob(".st.json.*"))  # the atomic write leaves no temporary files


def test_sim_flash_file_keeps_boot_count_across_processes_even_after_sigkill(tmp_path: Path) -> None:
    flash, status = tmp_path / "flash.json", tmp_path / "st.json"
    sim = SimProcess("--rate", "100", "--flash", str(flash), tmp_path=tmp_path)
    assert wait_for(lambda: flash.exists())  # written at switch-on, as firmware would
    sim.proc.kill()  # the cable is pulled: no clean shutdown
    sim.stop()
    r = _run("--rate", "100", "--duration", "0.1", "--flash", str(flash), "--status-json", str(status))
    assert r.returncode == 0, r.stderr
    assert json.loads(flash.read_text())["boot_count"] == 2 and read_status(status)["boot_count"] == 2


def test_sim_help_lists_the_options() -> None:
    r = subprocess.run([sys.executable, "-m", "gyrocal.cli", "sim", "--help"], capture_output=True, text=True)
    for flag in ("--link", "--pty-link", "--can-port", "--status-json", "--record", "--power-cycle-every",
                 "--nak-next", "--drop-acks", "--never-hello", "--garbage-rate", "--seed", "--duration"):
        assert flag in r.stdout
