"""Reader ``dataflash``: ArduPilot .bin DataFlash logs through pymavlink's DFReader.

What the IMU message holds (ArduPilot AP_InertialSensor::Write_IMU, units from its FMTU message):
``TimeUS`` [us since boot], ``I`` the IMU instance, ``GyrX/Y/Z`` [rad/s] and ``AccX/Y/Z``
[m/s^2] as ``get_gyro(i)``/``get_accel(i)`` return them, i.e. in the body frame *after* the
calibrated offsets, scale factors and board orientation (and, on boards with it, the temperature
calibration) and after the INS low-pass filters (INS_GYRO_FILTER, INS_ACCEL_FILTER), and ``T``
the sensor temperature [degC]. It is logged at the main loop rate at most. Old logs name the
instances IMU, IMU2, IMU3 instead of the ``I`` field; both are read. Older firmware labels its
fields otherwise: ``TimeMS`` [ms since boot] before ``TimeUS`` (Copter 3.2, Solo), and ``Temp``
before ``T`` (Copter 3.3-3.6); a board with no temperature sensor logs ``Temp`` as 0.0. Those logs
crashed the reader, or lost their temperature with no word (a foreign-log audit).
"""

from __future__ import annotations

import numpy as np

from gyrocal.errors import LogFormatError
from gyrocal.logformat import LogData
from gyrocal.readers import ReadOptions, require
from gyrocal.readers.imu import si_imu_log


def read_dataflash(path: str, options: ReadOptions) -> LogData:
    """One IMU instance of an ArduPilot .bin as log columns."""
    require("pymavlink", "reading ArduPilot .bin logs")
    from pymavlink import DFReader

    inst = options.instance
    old_name = "IMU" if inst == 0 else f"IMU{inst + 1}"
    old_names = ["IMU", "IMU2", "IMU3"]
    try:
        df = DFReader.DFReader_binary(path, zero_time_base=True)
    except OSError as err:
        raise LogFormatError(f"{path}: cannot open the log ({err.strerror})") from err
    except Exception as err:  # DFReader raises what its parsing hits on a damaged file
        raise LogFormatError(f"{path}: pymavlink cannot read it as a DataFlash log ({err})") from err
    rows: list[tuple[float, ...]] = []
    seen: set[int] = set()
    other = 0
    while True:
        try:
            m = df.recv_match(type=old_names)
        except Exception as err:  # as above
            raise LogFormatError(f"{path}: DataFlash record unreadable ({err})") from err
        if m is None:
            break
        d = m.to_dict()
        kind = m.get_type()
        i = int(d["I"]) if "I" in d else old_names.index(kind)
        seen.add(i)
        if i != inst or (kind != "IMU" and "I" in d) or (kind != old_name and "I" not in d):
            other += 1
            continue
        if "TimeUS" in d:
            t_s = d["TimeUS"] * 1e-6
        elif "TimeMS" in d:
            t_s = d["TimeMS"] * 1e-3
        else:
            raise LogFormatError(f"{path}: {kind} record without TimeUS or TimeMS (its fields: "
                                 f"{', '.join(k for k in d if k != 'mavpackettype')}); not a layout this "
                                 "reader knows")
        rows.append((t_s, d["GyrX"], d["GyrY"], d["GyrZ"], d["AccX"], d["AccY"], d["AccZ"],
                     d.get("T", d.get("Temp", np.nan))))
    if not rows:
        raise LogFormatError(f"{path}: no IMU messages of instance {inst}; instances seen: "
                             f"{sorted(seen) or 'none'} (--instance N)")
    a = np.asarray(rows, dtype=np.float64)
    meta = {"sensor": f"ArduPilot IMU[{inst}]", "frame": "body",
            "correction": "after ArduPilot's offsets, scale and orientation"}
    meta["other_instance_records"] = str(other)
    temp = a[:, 7]
    warnings: list[str] = []
    if not np.isfinite(temp).any() or not np.any(temp[np.isfinite(temp)] != 0.0):
        why = "all 0.0: a board with no IMU temperature sensor" if np.isfinite(temp).any() else "none logged"
        warnings.append(f"{path}: IMU[{inst}] comes without a temperature ({why}); the log has no temp "
                        "column (a fit of temperature terms needs one)")
        temp = np.full(temp.shape, np.nan)
    log = si_imu_log(a[:, 0], a[:, 1:4], a[:, 4:7], temp, meta, path)
    log.warnings.extend(warnings)
    return log
