"""Reader ``dataflash``: ArduPilot .bin DataFlash logs through pymavlink's DFReader.

What the IMU message holds (ArduPilot AP_InertialSensor::Write_IMU, units from its FMTU message):
``TimeUS`` [us since boot], ``I`` the IMU instance, ``GyrX/Y/Z`` [rad/s] and ``AccX/Y/Z``
[m/s^2] as ``get_gyro(i)``/``get_accel(i)`` return them, i.e. in the body frame *after* the
calibrated offsets, scale factors and board orientation (and, on boards with it, the temperature
calibration) and after the INS low-pass filters (INS_GYRO_FILTER, INS_ACCEL_FILTER), and ``T``
the sensor temperature [degC]. It is logged at the main loop rate at most. Old logs name the
instances IMU, IMU2, IMU3 instead of the ``I`` field; both are read.
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
            m = df.recv_match(type=["IMU", old_name])
        except Exception as err:  # as above
            raise LogFormatError(f"{path}: DataFlash record unreadable ({err})") from err
        if m is None:
            break
        d = m.to_dict()
        i = int(d.get("I", 0 if m.get_type() == "IMU" else inst))
        seen.add(i)
        if i != inst or (m.get_type() != "IMU" and "I" in d):
            other += 1
            continue
        rows.append((d["TimeUS"] * 1e-6, d["GyrX"], d["GyrY"], d["GyrZ"], d["AccX"], d["AccY"], d["AccZ"],
                     d.get("T", np.nan)))
    if not rows:
        raise LogFormatError(f"{path}: no IMU messages of instance {inst}; instances seen: "
                             f"{sorted(seen) or 'none'} (--instance N)")
    a = np.asarray(rows, dtype=np.float64)
    meta = {"sensor": f"ArduPilot IMU[{inst}]", "frame": "body",
            "correction": "after ArduPilot's offsets, scale and orientation"}
    meta["other_instance_records"] = str(other)
    return si_imu_log(a[:, 0], a[:, 1:4], a[:, 4:7], a[:, 7], meta, path)
