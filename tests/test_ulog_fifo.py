"""PX4 sensor_gyro_fifo / sensor_accel_fifo: every raw FIFO sample, at its own time, in SI units
converted to deg/s and g, with the accel FIFO and the temperature of the same chip.

No public PX4 log with the FIFO topics was found (pyulog's six test logs have none), so the log is
written here from the ULog specification (tests/foreign_logs.write_ulog) and read with pyulog."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gyrocal.errors import LogFormatError
from gyrocal.readers import ReadOptions, read_any
from gyrocal.readers.ulog import expand_fifo
from tests.foreign_logs import write_ulog

pytest.importorskip("pyulog")
R2D, G0 = 180.0 / math.pi, 9.80665
DEV_A, DEV_B = 0x2A0025, 0x2B0125  # two chips: bus/address in the low 16 bits
ACC_A, ACC_B = 0x2C0025, 0x2D0125  # their accelerometers (another devtype, same bus/address)
GYRO_SCALE = math.radians(1 / 131)  # rad/s per count (ICM42688P high-res)
ACC_SCALE = G0 / 8192  # m/s^2 per count


def _fifo_rows(dev: int, scale: float, counts: np.ndarray, t0_us: int, dt_us: float = 250.0,
               per_msg: int = 4) -> list[dict]:
    """FIFO messages of ``counts`` (n, 3) raw samples, ``per_msg`` at a time; a message is stamped
    with its newest sample's time, as PX4's drivers do."""
    rows = []
    for m in range(0, len(counts), per_msg):
        block = counts[m:m + per_msg]
        n = len(block)
        arrays = {a: list(block[:, k]) + [0] * (32 - n) for k, a in enumerate("xyz")}
        t_last = t0_us + (m + n - 1) * dt_us
        rows.append({"timestamp": int(t_last) + 40, "timestamp_sample": int(t_last), "device_id": dev,
                     "dt": dt_us, "scale": scale, "samples": n, **arrays})
    return rows


def _avg_rows(dev: int, t_us: np.ndarray, temp: np.ndarray) -> list[dict]:
    return [{"timestamp": int(t) + 40, "timestamp_sample": int(t), "device_id": dev, "x": 0.0, "y": 0.0,
             "z": 0.0, "temperature": float(c), "error_count": 0, "clip_counter": [0, 0, 0], "samples": 4}
            for t, c in zip(t_us, temp, strict=True)]


@pytest.fixture(scope="module")
def fifo_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    rng = np.random.default_rng(4)
    n = 4000  # 1 s at 4 kHz
    t0 = 5_000_000
    g_a = rng.integers(-3000, 3000, (n, 3))
    g_b = rng.integers(-3000, 3000, (n, 3))
    acc_a = np.tile([100, -50, -8192], (n, 1)) + rng.integers(-20, 20, (n, 3))  # az = -1 g
    acc_b = np.tile([0, 0, 8192], (n, 1))  # the other chip, upside down: az = +1 g
    avg_t = t0 + np.arange(0, n, 4) * 250.0 + 750
    gyro_a_rows = _fifo_rows(DEV_A, GYRO_SCALE, g_a, t0)
    gyro_a_rows[100]["samples"] = 0  # a damaged message: dropped whole
    inst = [("sensor_gyro_fifo", 0, gyro_a_rows),
            ("sensor_gyro_fifo", 1, _fifo_rows(DEV_B, GYRO_SCALE, g_b, t0)),
            # accel FIFO instances in the other order: the chip decides, not the instance number
            ("sensor_accel_fifo", 0, _fifo_rows(ACC_B, ACC_SCALE, acc_b, t0)),
            ("sensor_accel_fifo", 1, _fifo_rows(ACC_A, ACC_SCALE, acc_a, t0 + 500, per_msg=8)),
            ("sensor_gyro", 0, _avg_rows(DEV_B, avg_t, np.full(avg_t.size, 50.0))),
            ("sensor_gyro", 1, _avg_rows(DEV_A, avg_t, np.linspace(30.0, 33.0, avg_t.size))),
            ("sensor_accel", 0, _avg_rows(ACC_A, avg_t, np.full(avg_t.size, 30.0))),
            ("sensor_accel", 1, _avg_rows(ACC_B, avg_t, np.full(avg_t.size, 50.0)))]
    path = tmp_path_factory.mktemp("ulog") / "fifo.ulg"
    write_ulog(path, inst)
    t = (t0 + np.arange(n) * 250.0) * 1e-6
    return path, {"t": t, "g_a": g_a, "acc_a": acc_a, "avg_t": avg_t * 1e-6}


def test_fifo_samples_expand_at_their_own_times(fifo_log: tuple[Path, dict]) -> None:
    path, truth = fifo_log
    log = read_any(path)
    assert log.metadata["sensor"] == "PX4 sensor_gyro_fifo[0]"
    assert log.metadata["accel_from"] == "sensor_accel_fifo[1]" and log.metadata["device_id"] == str(DEV_A)
    assert log.dropped["bad_fifo_messages"] == 1
    # the accel FIFO starts 0.5 ms later (t0 + 500 us): the two gyro samples before it have no accel
    assert log.dropped["no_accel"] == 2
    keep = np.ones(truth["t"].size, dtype=bool)
    keep[400:404] = False  # message 100's four samples
    keep[:2] = False
    np.testing.assert_allclose(log["t"], truth["t"][keep], rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.gyro_dps, truth["g_a"][keep] * np.float32(GYRO_SCALE) * R2D, rtol=1e-12)
    # accel: the same chip's FIFO, interpolated onto the gyro times (at most 0.5 ms apart), -1 g
    assert np.median(log["az"]) == pytest.approx(-1.0, abs=0.005)
    assert np.all(np.abs(log["ax"] - 100 * np.float32(ACC_SCALE) / G0) < 21 * ACC_SCALE / G0)
    # the temperature: sensor_gyro of the same device, interpolated (30 -> 33 degC)
    expect = np.interp(log["t"], truth["avg_t"], np.linspace(30.0, 33.0, truth["avg_t"].size))
    np.testing.assert_allclose(log["temp"], expect, atol=1e-5)


def test_other_instance_and_the_averaged_topic(fifo_log: tuple[Path, dict]) -> None:
    path, _ = fifo_log
    other = read_any(path, options=ReadOptions(instance=1))
    assert other.metadata["accel_from"] == "sensor_accel_fifo[0]"
    assert np.median(other["az"]) == pytest.approx(1.0, abs=1e-6) and np.allclose(other["temp"], 50.0)
    averaged = read_any(path, options=ReadOptions(topic="sensor_gyro", instance=1))
    assert averaged.metadata["sensor"] == "PX4 sensor_gyro[1]" and len(averaged) == 1000
    # the averaged topic pairs by chip too: sensor_gyro[1] is chip A, whose accel is sensor_accel[0]
    # (by instance number it took sensor_accel[1], chip B's, with no word: a foreign-log audit)
    assert averaged.metadata["accel_from"] == "sensor_accel[0]"
    first = read_any(path, options=ReadOptions(topic="sensor_gyro", instance=0))
    assert first.metadata["accel_from"] == "sensor_accel[1]"
    # an instance that is not logged is refused, not read from sensor_combined (the primary IMU)
    with pytest.raises(LogFormatError, match=r"instance 3 is not logged"):
        read_any(path, options=ReadOptions(instance=3))
    with pytest.raises(LogFormatError, match=r"instances logged: \[0, 1\]"):
        read_any(path, options=ReadOptions(topic="sensor_gyro_fifo", instance=3))


def test_expand_fifo_counts_a_bad_message_and_orders_samples() -> None:
    class D:
        data = {"samples": np.array([3, 40, 2]), "dt": np.array([100.0, 100.0, 100.0]),
                "timestamp_sample": np.array([1000, 2000, 3000]), "scale": np.array([0.5, 0.5, 2.0]),
                **{f"{a}[{i}]": np.array([i + 1, 7, -(i + 1)]) for a in "xyz" for i in range(32)}}

    t, v, bad = expand_fifo(D())
    assert bad == 1
    np.testing.assert_allclose(t * 1e6, [800, 900, 1000, 2900, 3000])
    np.testing.assert_allclose(v[:, 0], [0.5, 1.0, 1.5, -2.0, -4.0])


def test_old_fifo_in_the_sensor_frame_is_refused(tmp_path: Path) -> None:
    """Older PX4: a ``rotation`` field the consumer applied; samples not in the board frame."""
    from tests.foreign_logs import ULOG_TOPICS

    old = {"sensor_gyro_fifo": [*ULOG_TOPICS["sensor_gyro_fifo"], ("uint8_t", "rotation")]}
    rows = _fifo_rows(DEV_A, GYRO_SCALE, np.zeros((400, 3), dtype=int), 1_000_000)
    acc = _fifo_rows(ACC_A, ACC_SCALE, np.tile([0, 0, -8192], (400, 1)), 1_000_000)
    for rotation, name in ((4, "yaw180.ulg"), (0, "none.ulg")):  # 4: ROTATION_YAW_180
        for r in rows:
            r["rotation"] = rotation
        path = tmp_path / name
        write_ulog(path, [("sensor_gyro_fifo", 0, rows), ("sensor_accel_fifo", 0, acc)], fields=old)
        if rotation:
            with pytest.raises(LogFormatError, match="rotation 4 not applied.*--topic sensor_gyro"):
                read_any(path)
        else:
            assert len(read_any(path)) == 400
