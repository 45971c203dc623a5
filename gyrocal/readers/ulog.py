"""Reader ``ulog``: PX4 .ulg logs through pyulog (``pip install 'gyrocal[formats]'``).

Which fields, and what they hold (PX4 msg/SensorGyro.msg, SensorAccel.msg, SensorCombined.msg):

- ``sensor_gyro`` (per instance = per physical IMU): ``x y z`` angular velocity in the FRD *board*
  frame [rad/s], as the driver publishes it (PX4Gyroscope::update/updateFIFO: rotated, scaled,
  and averaged over the FIFO's raw samples, *before* the sensors module applies the offset and
  thermal calibration), ``temperature`` [degC],
  ``timestamp_sample`` [us]. ``sensor_accel`` the same in m/s^2. This is what a drift calibrator
  wants: the sensor's own output with its temperature.
- ``sensor_combined`` (the selected IMU only): ``gyro_rad[3]`` [rad/s] and
  ``accelerometer_m_s2[3]`` in the body frame, *after* calibration, no temperature. Used only
  when no instance of sensor_gyro has enough samples (old logs, or a profile that logs sensor_gyro
  at a few Hz), with a warning saying so.

- ``sensor_gyro_fifo`` / ``sensor_accel_fifo`` (PX4 msg/SensorGyroFifo.msg, SensorAccelFifo.msg;
  logged with SDLOG_PROFILE's high-rate raw IMU bit): every raw sample of the sensor's FIFO, not
  the average: ``samples`` (1..32) int16 counts per axis in ``x y z[32]``, in the FRD board frame
  (the driver's rotation applied: PX4Gyroscope/PX4Accelerometer::updateFIFO), before any
  calibration; value = count * ``scale`` [rad/s or m/s^2 per count]; ``dt`` [us] between
  samples; ``timestamp_sample`` [us] is the time of the newest sample, the last in the arrays
  (the drivers stamp the batch with the FIFO watermark interrupt, e.g. ICM42688P::RunImpl), so
  sample n is at ``timestamp_sample - (samples - 1 - n) * dt``. No temperature: it comes from
  sensor_gyro of the same ``device_id``, interpolated. The accel FIFO of the same chip (same
  bus, address: ``device_id & 0xFFFF``) is expanded likewise and interpolated onto the gyro's
  times. Read by default when logged (``--topic sensor_gyro`` reads the averages instead). Older
  PX4 versions left the FIFO samples in the sensor's frame with a ``rotation`` field for the
  consumer (VehicleAngularVelocity) to apply: such a log is refused unless the rotation is 0.

Accel is interpolated onto the gyro's sample times; gyro samples outside the accel's time span are
dropped and counted as ``no_accel``. Time is ``timestamp_sample`` (else ``timestamp``) in s since boot.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gyrocal.errors import ConfigError, LogFormatError
from gyrocal.logformat import LogData
from gyrocal.readers import ReadOptions, require
from gyrocal.readers.imu import si_imu_log

MIN_SAMPLES = 100
"""Fewer sensor_gyro samples than this (a topic logged at a few Hz) is not a log to fit."""


def _topic(ulog: Any, name: str, instance: int) -> Any:
    for d in ulog.data_list:
        if d.name == name and d.multi_id == instance:
            return d
    return None


def _time_s(d: Any) -> np.ndarray:
    ts = d.data.get("timestamp_sample", d.data["timestamp"])
    return np.asarray(ts, dtype=np.float64) * 1e-6


FIFO_LEN = 32
"""Samples a FIFO message holds at most (``x[32]``)."""
TOPICS = ("sensor_gyro_fifo", "sensor_gyro", "sensor_combined")


def expand_fifo(d: Any) -> tuple[np.ndarray, np.ndarray, int]:
    """One sample per row from a sensor_gyro_fifo / sensor_accel_fifo topic's messages.

    Returns (time [s], values (n, 3) in the topic's SI unit, messages dropped): sample n of a
    message is at ``timestamp_sample - (samples - 1 - n) * dt`` and holds ``x[n] * scale``. A
    message with ``samples`` outside 1..32, or a non-positive ``dt``, is dropped whole.
    """
    n = np.asarray(d.data["samples"], dtype=np.int64)
    dt = np.asarray(d.data["dt"], dtype=np.float64)
    ok = (n >= 1) & (n <= FIFO_LEN) & (dt > 0)
    k = np.arange(FIFO_LEN)
    valid = ok[:, None] & (k[None, :] < n[:, None])
    t_us = (np.asarray(d.data["timestamp_sample"], dtype=np.float64)[:, None]
            - (n[:, None] - 1 - k[None, :]) * dt[:, None])
    scale = np.asarray(d.data["scale"], dtype=np.float64)[:, None]
    axes = [np.column_stack([d.data[f"{a}[{i}]"] for i in range(FIFO_LEN)]).astype(np.float64) * scale
            for a in "xyz"]
    return t_us[valid] * 1e-6, np.column_stack([ax[valid] for ax in axes]), int((~ok).sum())


def _same_chip(ulog: Any, name: str, device_id: int) -> Any:
    """The topic instance on the same chip (bus and address: ``device_id & 0xFFFF``), or None."""
    for d in ulog.data_list:
        if d.name == name and "device_id" in d.data and len(d.data["device_id"]) \
                and int(d.data["device_id"][0]) & 0xFFFF == device_id & 0xFFFF:
            return d
    return None


def _read_fifo(ulog: Any, gyro_fifo: Any, inst: int, path: str) -> LogData:
    """sensor_gyro_fifo of one instance, with its chip's accel FIFO and sensor_gyro temperature."""
    dev = int(gyro_fifo.data["device_id"][0])
    for d in (gyro_fifo, _same_chip(ulog, "sensor_accel_fifo", dev)):
        if d is not None and "rotation" in d.data and np.any(np.asarray(d.data["rotation"]) != 0):
            rot = int(np.max(d.data["rotation"]))
            raise LogFormatError(f"{path}: {d.name}[{d.multi_id}] holds samples in the sensor's own frame "
                                 f"(rotation {rot} not applied, as older PX4 left it); read the board-frame "
                                 "averages with --topic sensor_gyro")
    tg, g, bad_g = expand_fifo(gyro_fifo)
    warnings: list[str] = []
    dropped = {"bad_fifo_messages": bad_g} if bad_g else {}
    acc = _same_chip(ulog, "sensor_accel_fifo", dev) or _topic(ulog, "sensor_accel_fifo", inst)
    if acc is not None:
        ta, a_raw, bad_a = expand_fifo(acc)
        accel_src = f"sensor_accel_fifo[{acc.multi_id}]"
        if bad_a:
            dropped["bad_accel_fifo_messages"] = bad_a
    else:
        acc = _same_chip(ulog, "sensor_accel", dev) or _topic(ulog, "sensor_accel", inst)
        if acc is None:
            raise LogFormatError(f"{path}: sensor_gyro_fifo[{inst}] has no accel: neither sensor_accel_fifo "
                                 "nor sensor_accel is logged for its chip")
        ta = _time_s(acc)
        a_raw = np.column_stack([acc.data[k] for k in "xyz"]).astype(np.float64)
        accel_src = f"sensor_accel[{acc.multi_id}] (averaged)"
    order = np.argsort(ta, kind="stable")
    ta, a_raw = ta[order], a_raw[order]
    inside = (tg >= ta[0]) & (tg <= ta[-1]) if ta.size else np.zeros(tg.size, dtype=bool)
    a = np.column_stack([np.interp(tg[inside], ta, a_raw[:, k]) for k in range(3)])
    temp = None
    gyro = _same_chip(ulog, "sensor_gyro", dev)
    if gyro is not None and "temperature" in gyro.data:
        tt = _time_s(gyro)
        tv = np.asarray(gyro.data["temperature"], dtype=np.float64)
        fin = np.isfinite(tv)
        if fin.any():
            o = np.argsort(tt[fin], kind="stable")
            temp = np.interp(tg[inside], tt[fin][o], tv[fin][o])
    if temp is None:
        warnings.append(f"{path}: no sensor_gyro of device {dev} with a temperature; the log has no temp "
                        "column")
    meta = {"sensor": f"PX4 sensor_gyro_fifo[{gyro_fifo.multi_id}]", "frame": "FRD board",
            "correction": "before PX4 calibration (raw FIFO samples)", "device_id": str(dev),
            "accel_from": accel_src}
    dropped["no_accel"] = int((~inside).sum())
    log = si_imu_log(tg[inside], g[inside], a, temp, meta, path, dropped)
    log.warnings.extend(warnings)
    return log


def read_ulog(path: str, options: ReadOptions) -> LogData:
    """One IMU instance of a .ulg as log columns (see the module docstring for which fields)."""
    pyulog = require("pyulog", "reading PX4 .ulg logs")
    try:
        ulog = pyulog.ULog(path, ["sensor_gyro", "sensor_accel", "sensor_combined", "sensor_gyro_fifo",
                                  "sensor_accel_fifo"])
    except OSError as err:
        raise LogFormatError(f"{path}: cannot open the log ({err.strerror})") from err
    except Exception as err:  # pyulog raises its own ULogException, and others on a damaged file
        raise LogFormatError(f"{path}: pyulog cannot read it as a ULog ({err})") from err
    inst = options.instance
    topic = options.topic
    if topic not in (None, *TOPICS):
        raise ConfigError(f"--topic {topic!r}: a .ulg is read from {', '.join(TOPICS)}")
    fifo = _topic(ulog, "sensor_gyro_fifo", inst)
    if topic == "sensor_gyro_fifo" or (topic is None and fifo is not None):
        if fifo is None:
            have_fifo = sorted({d.multi_id for d in ulog.data_list if d.name == "sensor_gyro_fifo"})
            raise LogFormatError(f"{path}: no sensor_gyro_fifo instance {inst}; instances logged: "
                                 f"{have_fifo or 'none'} (--instance N)")
        return _read_fifo(ulog, fifo, inst, path)
    gyro, accel = _topic(ulog, "sensor_gyro", inst), _topic(ulog, "sensor_accel", inst)
    have = sorted({d.multi_id for d in ulog.data_list if d.name == "sensor_gyro"})
    meta = {"sensor": f"PX4 sensor_gyro[{inst}]", "frame": "FRD board",
            "correction": "before PX4 calibration (driver output)"}
    warnings: list[str] = []
    use_raw = topic == "sensor_gyro" or (topic is None and gyro is not None and accel is not None
                                           and len(gyro.data["timestamp"]) >= MIN_SAMPLES)
    if use_raw:
        if gyro is None or accel is None:
            raise LogFormatError(f"{path}: no sensor_gyro/sensor_accel instance {inst}; "
                                 f"instances logged: {have or 'none'} (--instance N)")
        # the accelerometer of the gyro's own chip (bus and address), as the FIFO path does: instance
        # numbers of sensor_gyro and sensor_accel need not match (a log with them swapped paired a gyro
        # with another chip's accel, with no word: a foreign-log audit)
        ids = gyro.data.get("device_id")
        dev = int(ids[0]) if ids is not None and len(ids) else None
        mate = _same_chip(ulog, "sensor_accel", dev) if dev is not None else None
        if mate is not None:
            accel = mate
        elif dev is not None:
            warnings.append(f"{path}: no sensor_accel of sensor_gyro[{inst}]'s chip (device_id 0x{dev:x}) is "
                            f"logged; sensor_accel[{accel.multi_id}] is used, which may be another chip")
        meta["accel_from"] = f"sensor_accel[{accel.multi_id}]"
        tg, ta = _time_s(gyro), _time_s(accel)
        a_raw = np.column_stack([accel.data[k] for k in "xyz"]).astype(np.float64)
        inside = (tg >= ta[0]) & (tg <= ta[-1]) if ta.size else np.zeros(tg.size, dtype=bool)
        a = np.column_stack([np.interp(tg[inside], ta, a_raw[:, k]) for k in range(3)])
        g = np.column_stack([gyro.data[k] for k in "xyz"])[inside]
        temp = np.asarray(gyro.data["temperature"], dtype=np.float64)[inside]
        if "device_id" in gyro.data:
            meta["device_id"] = str(int(gyro.data["device_id"][0]))
        log = si_imu_log(tg[inside], g, a, temp, meta, path, {"no_accel": int((~inside).sum())})
    else:
        if inst != 0 and topic is None:
            # sensor_combined is the primary IMU, not instance N: refused, as .bin and .tlog refuse an
            # instance they do not hold (it was read in its place with no word of that)
            why = "not logged" if gyro is None or accel is None else \
                f"logged at {len(gyro.data['timestamp'])} samples only (< {MIN_SAMPLES})"
            raise LogFormatError(f"{path}: sensor_gyro/sensor_accel instance {inst} is {why}; instances "
                                 f"logged: {have or 'none'} (--instance N); sensor_combined holds the "
                                 "primary IMU only (--instance 0)")
        comb = _topic(ulog, "sensor_combined", 0)
        if comb is None:
            raise LogFormatError(f"{path}: neither sensor_gyro+sensor_accel (instance {inst}) nor "
                                 "sensor_combined is logged; nothing to read")
        n_raw = 0 if gyro is None else len(gyro.data["timestamp"])
        if topic is None:
            warnings.append(f"{path}: sensor_gyro[{inst}] has {n_raw} samples (< {MIN_SAMPLES}); reading "
                            "sensor_combined instead: the primary IMU (whichever instance PX4 chose), body "
                            "frame, AFTER PX4's calibration, no temperature")
        t = np.asarray(comb.data["timestamp"], dtype=np.float64) * 1e-6
        g = np.column_stack([comb.data[f"gyro_rad[{k}]"] for k in range(3)])
        a = np.column_stack([comb.data[f"accelerometer_m_s2[{k}]"] for k in range(3)])
        meta = {"sensor": "PX4 sensor_combined", "frame": "FRD body",
                "correction": "after PX4 calibration"}
        log = si_imu_log(t, g, a, None, meta, path)
    log.warnings.extend(warnings)
    return log
