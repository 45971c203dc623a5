"""Writers of small foreign logs for the reader tests: ArduPilot DataFlash .bin and rosbag2.

They write what the formats' own specifications say (DataFlash: FMT records then data records,
each with the 0xA3 0x95 header; rosbag2 through rosbags' Writer), so the readers are checked
against the libraries that read real logs, pymavlink and rosbags.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

HEAD = b"\xa3\x95"
IMU_FMT = "QBffffffIIf"
IMU_COLS = "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T"
_STRUCT = {"Q": "Q", "B": "B", "f": "f", "I": "I", "n": "4s", "N": "16s", "Z": "64s"}


def _fmt_record(msg_type: int, name: str, fmt: str, cols: str) -> bytes:
    length = 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in fmt))
    body = struct.pack("<BB4s16s64s", msg_type, length, name.encode(), fmt.encode(), cols.encode())
    return HEAD + bytes([128]) + body


def write_dataflash(path: Path, t_s: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                    temp_c: np.ndarray, instances: int = 1) -> None:
    """IMU records [rad/s, m/s^2, degC] for ``instances`` IMUs (instance k adds 0.01 k rad/s to x)."""
    out = bytearray(_fmt_record(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
    out += _fmt_record(200, "IMU", IMU_FMT, IMU_COLS)
    for i in range(len(t_s)):
        for k in range(instances):
            g = gyro_rad_s[i]
            out += HEAD + bytes([200]) + struct.pack(
                "<QBffffffIIf", int(round(t_s[i] * 1e6)), k, g[0] + 0.01 * k, g[1], g[2],
                *accel_m_s2[i], 0, 0, temp_c[i])
    Path(path).write_bytes(bytes(out))


def write_rosbag(path: Path, t_s: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                 temp_c: np.ndarray | None = None, topic: str = "/imu", mcap: bool = False) -> None:
    """A rosbag2 directory (sqlite3 or MCAP storage) with sensor_msgs/msg/Imu on ``topic``
    (+ /imu_temp Temperature)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    Imu, Header = ts.types["sensor_msgs/msg/Imu"], ts.types["std_msgs/msg/Header"]
    Time, V3 = ts.types["builtin_interfaces/msg/Time"], ts.types["geometry_msgs/msg/Vector3"]
    Quat, Temp = ts.types["geometry_msgs/msg/Quaternion"], ts.types["sensor_msgs/msg/Temperature"]
    z9 = np.zeros(9)
    storage = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
    with Writer(path, version=8, storage_plugin=storage) as w:
        conn = w.add_connection(topic, Imu.__msgtype__, typestore=ts)
        tconn = w.add_connection("/imu_temp", Temp.__msgtype__, typestore=ts) if temp_c is not None else None
        for i, t in enumerate(t_s):
            ns = int(round(t * 1e9))
            stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
            g, a = gyro_rad_s[i], accel_m_s2[i]
            m = Imu(header=Header(stamp=stamp, frame_id="imu_link"),
                    orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=z9, angular_velocity=V3(x=g[0], y=g[1], z=g[2]),
                    angular_velocity_covariance=z9, linear_acceleration=V3(x=a[0], y=a[1], z=a[2]),
                    linear_acceleration_covariance=z9)
            w.write(conn, ns, ts.serialize_cdr(m, Imu.__msgtype__))
            if tconn is not None and i % 10 == 0:
                tm = Temp(header=Header(stamp=stamp, frame_id="imu_link"), temperature=float(temp_c[i]),
                          variance=0.0)
                w.write(tconn, ns, ts.serialize_cdr(tm, Temp.__msgtype__))


def write_rosbag1(path: Path, t_s: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray) -> None:
    """A ROS 1 .bag with sensor_msgs/Imu on /imu (rosbags' rosbag1 Writer, ROS 1 serialisation)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    Imu, Header = ts.types["sensor_msgs/msg/Imu"], ts.types["std_msgs/msg/Header"]
    Time, V3 = ts.types["builtin_interfaces/msg/Time"], ts.types["geometry_msgs/msg/Vector3"]
    Quat = ts.types["geometry_msgs/msg/Quaternion"]
    z9 = np.zeros(9)
    with Writer(path) as w:
        conn = w.add_connection("/imu", Imu.__msgtype__, typestore=ts)
        for i, t in enumerate(t_s):
            ns = int(round(t * 1e9))
            g, a = gyro_rad_s[i], accel_m_s2[i]
            m = Imu(header=Header(seq=i, stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000),
                                  frame_id="imu"),
                    orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=z9,
                    angular_velocity=V3(x=g[0], y=g[1], z=g[2]), angular_velocity_covariance=z9,
                    linear_acceleration=V3(x=a[0], y=a[1], z=a[2]), linear_acceleration_covariance=z9)
            w.write(conn, ns, ts.serialize_ros1(m, Imu.__msgtype__))
