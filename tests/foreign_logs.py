"""Writers of small foreign logs for the reader tests: ArduPilot DataFlash .bin, rosbag2, PX4 ULog.

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


OLD_IMU_FMT = "IffffffIIf"
OLD_IMU_COLS = "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,ErrG,ErrA,Temp"


def write_dataflash(path: Path, t_s: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                    temp_c: np.ndarray, instances: int = 1, old: bool = False) -> None:
    """IMU records [rad/s, m/s^2, degC] for ``instances`` IMUs (instance k adds 0.01 k rad/s to x).

    ``old``: the layout of Copter 3.2 and Solo logs, one message per IMU (IMU, IMU2, IMU3) with no
    ``I`` field, ``TimeMS`` [ms] and ``Temp`` [degC] (ArduPilot's LogStructure.h of that time)."""
    out = bytearray(_fmt_record(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
    if old:
        for k in range(instances):
            out += _fmt_record(200 + k, "IMU" if k == 0 else f"IMU{k + 1}", OLD_IMU_FMT, OLD_IMU_COLS)
    else:
        out += _fmt_record(200, "IMU", IMU_FMT, IMU_COLS)
    for i in range(len(t_s)):
        for k in range(instances):
            g = gyro_rad_s[i]
            if old:
                out += HEAD + bytes([200 + k]) + struct.pack(
                    "<IffffffIIf", int(round(t_s[i] * 1e3)), g[0] + 0.01 * k, g[1], g[2],
                    *accel_m_s2[i], 0, 0, temp_c[i])
            else:
                out += HEAD + bytes([200]) + struct.pack(
                    "<QBffffffIIf", int(round(t_s[i] * 1e6)), k, g[0] + 0.01 * k, g[1], g[2],
                    *accel_m_s2[i], 0, 0, temp_c[i])
    Path(path).write_bytes(bytes(out))


def write_rosbag(path: Path, t_s: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                 temp_c: np.ndarray | None = None, topic: str = "/imu", mcap: bool = False,
                 zero_stamps: bool = False) -> None:
    """A rosbag2 directory (sqlite3 or MCAP storage) with sensor_msgs/msg/Imu on ``topic``
    (+ /imu_temp Temperature); ``zero_stamps``: every header.stamp 0, as a driver that never sets
    it writes, the record times still ``t_s``."""
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
            stamp = Time(sec=0, nanosec=0) if zero_stamps else Time(sec=ns // 1_000_000_000,
                                                                     nanosec=ns % 1_000_000_000)
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


# ULog (PX4's log format, docs.px4.io "ULog File Format"): a 16-byte header, then messages of
# {uint16 size, uint8 type, body}: 'B' flag bits, 'F' formats, 'A' subscriptions, 'D' data.
_ULOG_TYPES = {"uint64_t": "Q", "uint32_t": "I", "int16_t": "h", "uint8_t": "B", "float": "f"}
ULOG_TOPICS = {
    "sensor_gyro_fifo": [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
                         ("uint32_t", "device_id"), ("float", "dt"), ("float", "scale"), ("int16_t[32]", "x"),
                         ("int16_t[32]", "y"), ("int16_t[32]", "z"), ("uint8_t", "samples")],
    "sensor_gyro": [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"),
                    ("float", "x"), ("float", "y"), ("float", "z"), ("float", "temperature"),
                    ("uint32_t", "error_count"), ("uint8_t[3]", "clip_counter"), ("uint8_t", "samples")],
}
ULOG_TOPICS["sensor_accel_fifo"] = ULOG_TOPICS["sensor_gyro_fifo"]
ULOG_TOPICS["sensor_accel"] = ULOG_TOPICS["sensor_gyro"]


def _ulog_msg(kind: str, body: bytes) -> bytes:
    return struct.pack("<HB", len(body), ord(kind)) + body


def _ulog_pack(fields: list[tuple[str, str]], row: dict) -> bytes:
    out = b""
    for ftype, name in fields:
        base, _, n = ftype.partition("[")
        code = _ULOG_TYPES[base]
        if n:
            out += struct.pack(f"<{int(n[:-1])}{code}", *row[name])
        else:
            out += struct.pack("<" + code, row[name])
    return out


def write_ulog(path: Path, instances: list[tuple[str, int, list[dict]]],
               fields: dict[str, list[tuple[str, str]]] | None = None) -> None:
    """A ULog file holding, for each (topic of ULOG_TOPICS, multi_id, rows), its messages; a row
    gives every field (arrays as sequences); messages are written in time order. ``fields``
    overrides a topic's field list (e.g. an older PX4's)."""
    spec_of = {**ULOG_TOPICS, **(fields or {})}
    out = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0))
    out += _ulog_msg("B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
    for name in sorted({t for t, _, _ in instances}):
        spec = ";".join(f"{ftype} {fname}" for ftype, fname in spec_of[name]) + ";"
        out += _ulog_msg("F", f"{name}:{spec}".encode())
    data: list[tuple[int, int, bytes]] = []
    for msg_id, (name, multi_id, rows) in enumerate(instances):
        out += _ulog_msg("A", struct.pack("<BH", multi_id, msg_id) + name.encode())
        for k, row in enumerate(rows):
            body = struct.pack("<H", msg_id) + _ulog_pack(spec_of[name], row)
            data.append((int(row["timestamp"]), msg_id * 10**9 + k, _ulog_msg("D", body)))
    for _, _, msg in sorted(data):
        out += msg
    Path(path).write_bytes(bytes(out))
