"""End to end: ``gyrocal run`` with ``link.kind: mavlink`` calibrates a virtual ArduPilot as it warms."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from gyrocal.mavlink.poly import evaluate  # noqa: E402
from gyrocal.mavlink.profiles import ArduPilot  # noqa: E402
from gyrocal.sim.autopilot import VirtualAutopilot  # noqa: E402
from gyrocal.sim.autopilot_truth import offset_errors  # noqa: E402
from tests.sim_helpers import SimProcess, read_status, wait_for  # noqa: E402

pytestmark = pytest.mark.slow


def daemon_status(sock: Path) -> dict:
    out = subprocess.run(
        [sys.executable, "-m", "gyrocal.cli", "status", "--socket", str(sock), "--json"],
        capture_output=True,
        text=True,
    )
    return json.loads(out.stdout) if out.returncode == 0 and out.stdout.strip() else {}


def run_daemon_until_acked(tmp_path: Path, *sim_args: str) -> tuple[dict, dict]:
    """``gyrocal sim --link mavlink --autopilot ardupilot`` (warm-up tau 20 s) and ``gyrocal run`` until
    the daemon's first acked push; returns the autopilot's parameters then (its status JSON) and the
    daemon's status."""
    with SimProcess(
        "--link",
        "mavlink",
        "--autopilot",
        "ardupilot",
        "--rate",
        "250",
        "--warmup-tau",
        "20",
        "--status-json",
        str(tmp_path / "ap.json"),
        *sim_args,
        tmp_path=tmp_path,
    ) as ap:
        cfg = {
            "link": {"kind": "mavlink", "url": ap.address, "mavlink": {"autopilot": "ardupilot"}},
            "virtual_unit": {"enabled": False},
            "estimator": {"terms": ["1", "temp", "temp^2"]},
            "state_dir": str(tmp_path / "state"),
            "control_socket": str(tmp_path / "ctl.sock"),
            "watchdog": False,
        }
        (tmp_path / "cfg.yaml").write_text(json.dumps(cfg))
        log = (tmp_path / "run.log").open("wb")
        daemon = subprocess.Popen(
            [sys.executable, "-m", "gyrocal.cli", "run", "--config", str(tmp_path / "cfg.yaml")],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        try:
            acked = wait_for(
                lambda: (
                    (daemon_status(tmp_path / "ctl.sock").get("last_push") or {}).get("status") == "acked"
                ),
                120,
                poll_s=1.0,
            )
            assert acked, (tmp_path / "run.log").read_text()[-3000:]
            st = daemon_status(tmp_path / "ctl.sock")
            assert st["link"]["kind"] == "mavlink" and st["link"]["autopilot"] == "ardupilot"
            assert wait_for(lambda: read_status(tmp_path / "ap.json")["params"]["INS_TCAL1_ENABLE"] == 1, 5)
        finally:
            daemon.terminate()
            daemon.wait(20)
            log.close()
        return read_status(tmp_path / "ap.json")["params"], st


def test_the_daemon_learns_and_pushes_the_temperature_polynomial(tmp_path: Path) -> None:
    params, _ = run_daemon_until_acked(tmp_path)
    # the offset left over the range the daemon saw, against the truth, before and after
    truth = VirtualAutopilot("ardupilot", 250, 0)
    truth.power_on()
    before = dict(truth.params)
    prof = ArduPilot(0)
    temps = np.linspace(params["INS_TCAL1_TMIN"], params["INS_TCAL1_TMAX"], 5)
    raw = truth.raw_offset_dps(temps)

    def worst(p: dict) -> np.ndarray:
        return np.max(np.abs(raw - evaluate(prof.applied(p), temps) - prof.clamp_adjust(p, temps)), axis=0)

    assert params["INS_TCAL1_TMAX"] - params["INS_TCAL1_TMIN"] > 5.0
    assert np.all(worst(params) < worst(before) / 5), (worst(before) * 3600, worst(params) * 3600)


def test_the_daemon_calibrates_a_board_mounted_rotated(tmp_path: Path) -> None:
    """AHRS_ORIENTATION 10 (roll 180, yaw 90: x and y swapped, z flipped). The virtual autopilot
    subtracts in the sensor frame and rotates its output by its own transcription of ArduPilot's
    Vector3::rotate; the truth is rotated the same way (autopilot_truth), so an unrotated or wrongly
    rotated push would leave the error, not cut it."""
    params, st = run_daemon_until_acked(tmp_path, "--rotation", "10", "--drop-param-values", "3")
    assert params["AHRS_ORIENTATION"] == 10
    # three lost echoes make the push outlast the protocol's 1 s ack timeout: the daemon waits the
    # autopilot's ack_within_s instead of resending into a running push (each resend was NAKed BUSY,
    # and the record said nak for a set the autopilot then held: an integrator's audit)
    log = (tmp_path / "run.log").read_text()
    assert st["last_push"]["attempts"] == 1 and "a push is already running" not in log, log[-3000:]
    assert st["unit_caps"]["ack_within_s"] == 8.0
    assert st["last_push"]["board_rotation"] == {"AHRS_ORIENTATION": 10.0}  # in the store record too
    assert params["INS_TCAL1_TMAX"] - params["INS_TCAL1_TMIN"] > 5.0
    temps = np.linspace(params["INS_TCAL1_TMIN"], params["INS_TCAL1_TMAX"], 5)
    res = offset_errors("ardupilot", 0, params, temps)
    assert res["board_rotation"] == 10
    assert min(res["improvement_x"]) > 5.0, res
    state = json.loads((tmp_path / "state" / "mavlink.json").read_text())
    assert [u["rotation"] for u in state["units"].values()] == [{"AHRS_ORIENTATION": 10.0}]


def test_demo_mavlink_calibrates_a_virtual_px4_and_says_it_needs_a_reboot() -> None:
    """`gyrocal demo --mavlink` (one autopilot, to keep the suite short): acked, offset error cut on each
    axis over the range seen, and the PX4's reboot-needed push reported (TC_G_ENABLE was 0 at boot)."""
    out = subprocess.run(
        [sys.executable, "-m", "gyrocal.cli", "demo", "--mavlink", "--autopilot", "px4", "--json"],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout)["px4"]
    assert res["acked"] and res["reboot_needed"]["version"] == res["version"]
    assert res["tmax_c"] - res["tmin_c"] > 5.0
    assert min(res["improvement_x"]) > 5.0, res


def test_an_autopilot_that_hangs_during_the_first_push_is_calibrated_when_it_answers(tmp_path: Path) -> None:
    """The ArduPilot hangs for 12 s at the 5th PARAM_SET of the daemon's first push (the same boot goes
    on). The session's read-back, cut by the hang, used to become a link fault: the retry of the same
    version was NAKed UNKNOWN_TERMS (final) and the autopilot stayed uncalibrated, its compensation
    off, for the switch-on. Now the read waits for the autopilot, and the retry is acked."""
    params, st = run_daemon_until_acked(tmp_path, "--silence-after-sets", "5", "--silence-for", "12")
    log = (tmp_path / "run.log").read_text()
    assert "heartbeat lost" in log and "read again when it answers" in log
    assert "UNKNOWN_TERMS" not in log and "push v1 ended: acked" in log


def test_an_autopilot_whose_imu_gives_no_temperature_is_a_fault_status_shows(tmp_path: Path) -> None:
    """RAW_IMU's temperature 0 ("not provided"): every sample was dropped and status said "learning the
    unit's noise level" for good, with no log line (an integrator's audit). After 10 s the link
    reports a fault that status and the journal name."""
    with SimProcess("--link", "mavlink", "--autopilot", "ardupilot", "--rate", "250", "--no-imu-temperature",
                    tmp_path=tmp_path) as ap:
        cfg = {
            "link": {"kind": "mavlink", "url": ap.address, "mavlink": {"autopilot": "ardupilot"}},
            "virtual_unit": {"enabled": False}, "estimator": {"terms": ["1", "temp", "temp^2"]},
            "state_dir": str(tmp_path / "state"), "control_socket": str(tmp_path / "ctl.sock"),
            "watchdog": False,
        }
        (tmp_path / "cfg.yaml").write_text(json.dumps(cfg))
        with (tmp_path / "run.log").open("wb") as log:
            daemon = subprocess.Popen([sys.executable, "-m", "gyrocal.cli", "run", "--config",
                                       str(tmp_path / "cfg.yaml")], stdout=log, stderr=subprocess.STDOUT)
            try:
                assert wait_for(lambda: "reports no temperature" in
                                (daemon_status(tmp_path / "ctl.sock").get("reason") or ""), 40, poll_s=1.0), \
                    (tmp_path / "run.log").read_text()[-2000:]
            finally:
                daemon.terminate()
                daemon.wait(20)
        text = (tmp_path / "run.log").read_text()
        assert text.count("reports no temperature") >= 1 and "Traceback" not in text


def test_an_autopilot_whose_parameter_answers_are_lost_mid_push_is_calibrated_when_they_return(
        tmp_path: Path) -> None:
    """For 12 s from the 5th PARAM_SET of the first push, the ArduPilot applies every write but no
    PARAM_VALUE reaches the daemon; heartbeats and RAW_IMU go on. The failed read-back became a link
    fault latched for good: every later write and read refused, the compensation left off (an
    integrator's audit). The link now reads again every 5 s, and the retry is acked."""
    params, st = run_daemon_until_acked(tmp_path, "--mute-params-after-sets", "5", "--silence-for", "12")
    log = (tmp_path / "run.log").read_text()
    assert "reading again every 5 s" in log and "are read again" in log
    assert "UNKNOWN_TERMS" not in log and "push v1 ended: acked" in log
