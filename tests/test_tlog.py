"""MAVLink .tlog: a real ArduSub telemetry log, and logs written with pymavlink's own encoder
(HIGHRES_IMU > SCALED_IMU(n) > RAW_IMU per instance, temperatures held, what is dropped and why)."""

from __future__ import annotations

import json
import math
import os
import struct
from pathlib import Path

import numpy as np
import pytest

from gyrocal.cli import main
from gyrocal.errors import LogFormatError
from gyrocal.readers import ReadOptions, accounting, detect_kind, read_any

DATA = Path(__file__).resolve().parent.parent / "data"
ARDUSUB = DATA / "ardusub_tlog" / "small.tlog"
R2D, G0 = 180.0 / math.pi, 9.80665


def _dialect():  # noqa: ANN202
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


class _Tlog:
    """Records of a .tlog: 8-byte big-endian time [us] + a packet from pymavlink's encoder."""

    def __init__(self) -> None:
        self.records: list[tuple[float, int, bytes]] = []
        self.mavs: dict[int, object] = {}

    def add(self, t_s: float, sysid: int, name: str, *fields: object) -> bytes:
        d = _dialect()
        mav = self.mavs.setdefault(sysid, d.MAVLink(None, srcSystem=sysid, srcComponent=1))
        packet = getattr(mav, f"{name.lower()}_encode")(*fields).pack(mav)
        mav.seq = (mav.seq + 1) % 256
        self.records.append((t_s, len(self.records), packet))
        return packet

    def write(self, path: Path) -> None:
        out = b"".join(struct.pack(">Q", int(1.7e15 + t * 1e6)) + p for t, _, p in sorted(self.records))
        path.write_bytes(out)


def _px4_like(tmp_path: Path) -> tuple[Path, dict]:
    """PX4-like: HIGHRES_IMU (id 0) at 100 Hz, SCALED_IMU/2 with temperatures, RAW_IMU at 10 Hz,
    a second vehicle, a GCS heartbeat, a record logged twice, a corrupt record, and a reboot."""
    log = _Tlog()
    truth: dict = {"t": [], "g": [], "a": []}
    boots = ((10.0, 2000), (1.0, 500))  # the second boot's clock restarts near 1 s
    for b, (t0, n) in enumerate(boots):
        base = sum(c for _, c in boots[:b]) * 0.01 + 100 * b  # file order: the reboot is later
        for i in range(n):
            t, tb = t0 + i * 0.01, base + i * 0.01
            g = (0.01 * math.sin(i / 50), -0.02, 0.003 * b)
            a = (0.1, -0.2, -G0)
            packet = log.add(tb, 1, "HIGHRES_IMU", int(round(t * 1e6)), *a, *g, 0, 0, 0, 1000, 0,
                             0, 21.5, 0xFFFF, 0)
            truth["t"].append(t)
            truth["g"].append(g)
            truth["a"].append(a)
            if i % 10 == 5:  # SCALED_IMU 0 at 10 Hz, just before sample 5, 15, ...: 30.00 degC + 0.01 k
                log.add(tb - 1e-4, 1, "SCALED_IMU", int(t * 1e3), 0, 0, -1000, 1, 2, 3, 0, 0, 0,
                        3000 + i // 10)
            if i % 2 == 0:  # SCALED_IMU2 (instance 1) at 50 Hz: gyro 5 mrad/s, -3 mrad/s, 0; 45 degC
                log.add(tb + 2e-4, 1, "SCALED_IMU2", int(t * 1e3), 10, -20, -1001, 5, -3, 0, 0, 0,
                        0, 4500)
            if i % 10 == 0:  # RAW_IMU id 0 at 10 Hz: lower priority than HIGHRES_IMU for instance 0
                log.add(tb + 3e-4, 1, "RAW_IMU", int(round(t * 1e6)), 0, 0, -1000, 1, 1, 1, 0, 0,
                        0, 0, 3100)
            if i == 700:  # the same HIGHRES_IMU logged twice
                log.records.append((tb + 4e-4, -1, packet))
            if i % 100 == 0:  # a second vehicle, and the ground station's heartbeat
                log.add(tb + 5e-4, 2, "HIGHRES_IMU", int(t * 1e6), 0, 0, -G0, 0, 0, 0, 0, 0, 0, 0,
                        0, 0, 20.0, 0, 0)
                log.add(tb + 6e-4, 255, "HEARTBEAT", 6, 8, 0, 0, 0, 3)
            if b == 0 and i == 1500:  # a corrupt record: one payload byte flipped, CRC fails
                p = bytearray(log.add(tb + 7e-4, 1, "HIGHRES_IMU", int(t * 1e6) + 500, 0, 0, -G0,
                                      0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0))
                p[12] ^= 0xFF
                log.records[-1] = (log.records[-1][0], log.records[-1][1], bytes(p))
    path = tmp_path / "px4.tlog"
    log.write(path)
    return path, {k: np.asarray(v, dtype=np.float64) for k, v in truth.items()}


def test_tlog_is_found_by_its_extension() -> None:
    assert detect_kind("flight.tlog") == "tlog"


def test_highres_imu_first_with_the_scaled_imu_temperature_held(tmp_path: Path) -> None:
    path, truth = _px4_like(tmp_path)
    log = read_any(path)
    assert log.metadata["sensor"] == "MAVLink HIGHRES_IMU[0]"
    assert log.metadata["temperature_from"] == "SCALED_IMU[0]"
    # what was left out, and why
    assert log.dropped["no_temperature"] == 5  # HIGHRES_IMU before the first SCALED_IMU
    assert log.dropped["lower_priority_scaled_imu"] == 250 and log.dropped["lower_priority_raw_imu"] == 250
    assert log.dropped["time_not_increasing"] == 1 and log.dropped["unreadable"] == 1
    assert log.dropped["other_source"] == 25
    # the first 5 HIGHRES_IMU after the reboot hold the last SCALED_IMU temperature from before it
    # (31.99 degC, where the new switch-on reads 30.00): a 2 degC step, dropped as the daemon drops it
    # (readers/plausible.py)
    assert log.dropped["implausible_temperature"] == 5
    assert len(log) == 2500 - 10 and accounting(log)["source_rows"] == len(log) + sum(log.dropped.values())
    # sessions: the reboot
    assert set(log["session"]) == {0.0, 1.0} and (log["session"] == 1).sum() == 495
    # units: rad/s -> deg/s and m/s^2 -> g (float32 on the wire)
    keep = np.ones(truth["t"].size, dtype=bool)
    keep[:5] = False
    keep[2000:2005] = False
    np.testing.assert_allclose(log["t"], truth["t"][keep], atol=1e-6)
    np.testing.assert_allclose(log.gyro_dps, truth["g"][keep] * R2D, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(log.accel_g, truth["a"][keep] / G0, rtol=1e-6, atol=1e-7)
    # the temperature: the last SCALED_IMU's, held (30.00 degC + 0.01 per 10 samples)
    assert log["temp"][0] == pytest.approx(30.0) and log["temp"][10] == pytest.approx(30.01)
    assert log["temp"][1994] == pytest.approx(30.0 + 0.01 * 199)


def test_scaled_imu_of_another_instance_with_its_own_temperature(tmp_path: Path) -> None:
    path, truth = _px4_like(tmp_path)
    log = read_any(path, options=ReadOptions(instance=1))
    assert log.metadata["sensor"] == "MAVLink SCALED_IMU2[1]" and not log.warnings
    assert len(log) == 1250 and set(log["session"]) == {0.0, 1.0}
    # mrad/s read at the centre of the int16 step, and mG -> g
    np.testing.assert_allclose(log["wx"], 5.5e-3 * R2D)
    np.testing.assert_allclose(log["wy"], -3.5e-3 * R2D)
    np.testing.assert_allclose(log["wz"], 0.0)
    np.testing.assert_allclose(log["az"], -1.0015)
    np.testing.assert_allclose(log["temp"], 45.0)
    with pytest.raises(LogFormatError, match="instance 2.*HIGHRES_IMU\\[0\\]"):
        read_any(path, options=ReadOptions(instance=2))


def test_a_px4_highres_imu_is_not_taken_for_imu_0(tmp_path: Path) -> None:
    """PX4 sends in HIGHRES_IMU the IMU it selected, with id never set (0), minus EKF2's gyro bias.
    After a failover to IMU 1, the reader took it for IMU 0 and gave it IMU 0's temperature from
    SCALED_IMU, another chip's (a foreign-log audit). IMU 0's own SCALED_IMU is read instead, and a
    HIGHRES_IMU asked for by --topic gets no temperature; both say why."""
    log = _Tlog()
    for i in range(1000):
        t = 5.0 + i * 0.01
        if i % 100 == 0:
            log.add(t, 1, "HEARTBEAT", 2, 12, 0, 0, 4, 3)  # MAV_AUTOPILOT_PX4
        # HIGHRES_IMU: IMU 1's 20 mrad/s on y, id 0
        log.add(t, 1, "HIGHRES_IMU", int(t * 1e6), 0, 0, -G0, 0, 0.02, 0, 0, 0, 0, 1000, 0, 0, 21.5,
                0x1FFF, 0)
        if i % 10 == 0:  # IMU 0: 10 mrad/s on x, 40 degC; IMU 1 at 60 degC
            log.add(t + 1e-4, 1, "SCALED_IMU", int(t * 1e3), 0, 0, -1000, 10, 0, 0, 0, 0, 0, 4000)
            log.add(t + 2e-4, 1, "SCALED_IMU2", int(t * 1e3), 0, 0, -1000, 0, 20, 0, 0, 0, 0, 6000)
    path = tmp_path / "px4.tlog"
    log.write(path)
    imu0 = read_any(path)
    assert imu0.metadata["sensor"] == "MAVLink SCALED_IMU[0]" and len(imu0) == 100
    np.testing.assert_allclose(imu0["wx"], 10.5e-3 * R2D)  # the step's centre
    np.testing.assert_allclose(imu0["temp"], 40.0)
    assert any("EKF2" in w and "SCALED_IMU[0]" in w for w in imu0.warnings)
    forced = read_any(path, options=ReadOptions(topic="HIGHRES_IMU"))
    assert forced.metadata["sensor"].startswith("MAVLink HIGHRES_IMU[0] (the IMU PX4 selected)")
    assert "EKF2" in forced.metadata["correction"] and "temp" not in forced.columns
    assert [w for w in forced.warnings if "EKF2" in w] and len(forced.warnings) == 1
    np.testing.assert_allclose(forced["wy"], 0.02 * R2D, rtol=1e-6)


def test_real_ardusub_tlog(capsys: pytest.CaptureFixture, tmp_path: Path) -> None:
    """ArduSub 4.1.1 via QGroundControl (data/PROVENANCE.md): RAW_IMU of IMU 0 at 2 Hz with its
    temperature; SCALED_IMU2 is all zeros (the vehicle has no second IMU)."""
    log = read_any(ARDUSUB)
    assert log.metadata["sensor"] == "MAVLink RAW_IMU[0]" and log.metadata["firmware"] == "4.1.1"
    assert len(log) == 528 and not log.dropped and set(log["session"]) == {0.0}
    assert np.all(np.diff(log["t"]) > 0) and 260 < log["t"][-1] - log["t"][0] < 265
    assert np.median(np.linalg.norm(log.accel_g, axis=1)) == pytest.approx(1.0, abs=0.03)
    assert np.median(log["az"]) < -0.95  # FRD body frame: a level vehicle reads -1 g
    assert 29.0 < log["temp"].min() < log["temp"].max() < 34.0
    assert np.abs(np.median(log.gyro_dps, axis=0)).max() < 1.5  # deg/s: a vehicle mostly at rest
    with pytest.raises(LogFormatError, match="SCALED_IMU2\\[1\\] all zero"):
        read_any(ARDUSUB, options=ReadOptions(instance=1))
    out = tmp_path / "ardusub.csv"
    assert main(["convert", str(ARDUSUB), str(out)]) == 0
    again = read_any(out)
    assert len(again) == 528 and again.metadata.get("source_format") == "tlog"
    capsys.readouterr()
    assert main(["fit", str(ARDUSUB), "--terms", "1", "--all-samples", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["samples"] == 528


def test_replay_reads_a_tlog(tmp_path: Path) -> None:
    from gyrocal.daemon.config import load_config
    from gyrocal.replay.run import replay
    from gyrocal.replay.source import open_recording

    state = tmp_path / "state"
    state.mkdir()
    cfg = load_config(None, {"state_dir": str(state), "control_socket": str(tmp_path / "c.sock"),
                             "watchdog": False})
    res = replay(open_recording(str(ARDUSUB)), cfg)
    assert res["format"] == "tlog" and res["samples"] == 528
