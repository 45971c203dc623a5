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


def read_ulog(path: str, options: ReadOptions) -> LogData:
    """One IMU instance of a .ulg as log columns (see the module docstring for which fields)."""
    pyulog = require("pyulog", "reading PX4 .ulg logs")
    try:
        ulog = pyulog.ULog(path, ["sensor_gyro", "sensor_accel", "sensor_combined"])
    except OSError as err:
        raise LogFormatError(f"{path}: cannot open the log ({err.strerror})") from err
    except Exception as err:  # pyulog raises its own ULogException, and others on a damaged file
        raise LogFormatError(f"{path}: pyulog cannot read it as a ULog ({err})") from err
    inst = options.instance
    topic = options.topic
    if topic not in (None, "sensor_gyro", "sensor_combined"):
        raise ConfigError(f"--topic {topic!r}: a .ulg is read from sensor_gyro or sensor_combined")
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
        comb = _topic(ulog, "sensor_combined", 0)
        if comb is None:
            raise LogFormatError(f"{path}: neither sensor_gyro+sensor_accel (instance {inst}) nor "
                                 "sensor_combined is logged; nothing to read")
        n_raw = 0 if gyro is None else len(gyro.data["timestamp"])
        if topic is None:
            warnings.append(f"{path}: sensor_gyro[{inst}] has {n_raw} samples (< {MIN_SAMPLES}); reading "
                            "sensor_combined instead: body frame, AFTER PX4's calibration, no temperature")
        t = np.asarray(comb.data["timestamp"], dtype=np.float64) * 1e-6
        g = np.column_stack([comb.data[f"gyro_rad[{k}]"] for k in range(3)])
        a = np.column_stack([comb.data[f"accelerometer_m_s2[{k}]"] for k in range(3)])
        meta = {"sensor": "PX4 sensor_combined", "frame": "FRD body",
                "correction": "after PX4 calibration"}
        log = si_imu_log(t, g, a, None, meta, path)
    log.warnings.extend(warnings)
    return log
