"""Reader ``rosbag``: rosbag2 bags (.mcap, .db3 or the bag directory) or ROS 1 .bag files holding
sensor_msgs/msg/Imu.

``sensor_msgs/Imu`` (REP 103/145): ``angular_velocity`` [rad/s] and ``linear_acceleration``
[m/s^2], the accelerometer's specific force (gravity included, +9.81 up at rest), in the frame
``header.frame_id``; time is ``header.stamp``, or the bag's record time when the stamps never move
(a driver that leaves them 0: its 4000 samples were all read at t = 0, with no word, by a foreign-log
audit), with a warning. The message has no temperature: a bag with one
sensor_msgs/msg/Temperature topic gets it interpolated onto the IMU times. Read with ``rosbags``
(pure Python, no ROS install).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gyrocal.errors import ConfigError, LogFormatError
from gyrocal.logformat import LogData
from gyrocal.readers import ReadOptions, require
from gyrocal.readers.imu import si_imu_log

IMU = "sensor_msgs/msg/Imu"
TEMP = "sensor_msgs/msg/Temperature"


def read_rosbag(path: str, options: ReadOptions) -> LogData:
    """One Imu topic of a rosbag2 or ROS 1 bag as log columns (``--topic`` when it holds several)."""
    require("rosbags", "reading ROS bags")
    from rosbags.highlevel import AnyReader

    p = Path(path)
    try:
        reader = AnyReader([p])
        reader.open()
    except Exception as err:  # rosbags raises its own error classes per storage
        raise LogFormatError(f"{path}: rosbags cannot open it as a rosbag2 bag ({err})") from err
    try:
        imus = [c for c in reader.connections if c.msgtype == IMU]
        topics = sorted({c.topic for c in imus})
        if not topics:
            raise LogFormatError(f"{path}: no {IMU} topic in the bag")
        topic = options.topic or (topics[0] if len(topics) == 1 else None)
        if topic not in topics:
            raise ConfigError(f"{path}: give --topic, one of {', '.join(topics)}")
        rows = []
        frame = ""
        try:
            for conn, rec_ns, raw in reader.messages(connections=[c for c in imus if c.topic == topic]):
                m = reader.deserialize(raw, conn.msgtype)
                st, w, a = m.header.stamp, m.angular_velocity, m.linear_acceleration
                rows.append((st.sec + st.nanosec * 1e-9, w.x, w.y, w.z, a.x, a.y, a.z, rec_ns * 1e-9))
                frame = m.header.frame_id
        except Exception as err:  # rosbags raises per storage and serialisation
            raise LogFormatError(f"{path}: message {len(rows) + 1} of {topic} unreadable ({err})") from err
        temps = [c for c in reader.connections if c.msgtype == TEMP]
        temp_t, temp_v = [], []
        if len(temps) == 1:
            for conn, rec_ns, raw in reader.messages(connections=temps):
                m = reader.deserialize(raw, conn.msgtype)
                temp_t.append((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, rec_ns * 1e-9))
                temp_v.append(m.temperature)
    finally:
        reader.close()
    if not rows:
        raise LogFormatError(f"{path}: topic {topic} holds no messages")
    arr = np.asarray(rows, dtype=np.float64)
    warnings: list[str] = []
    stamp_col = 0
    if arr.shape[0] > 1 and np.ptp(arr[:, 0]) == 0.0:
        stamp_col = 7
        warnings.append(f"{path}: every header.stamp of {topic} is {arr[0, 0]:g} s; the bag's record times "
                        "are used instead (they include the recorder's delays)")
    temp = None
    if len(temp_t) >= 1:
        tt = np.asarray(temp_t, dtype=np.float64)
        temp = np.interp(arr[:, stamp_col], tt[:, 1 if stamp_col else 0], np.asarray(temp_v))
    meta = {"sensor": f"ROS {topic}", "frame": frame, "correction": "as published",
            "time_from": "record time" if stamp_col else "header.stamp"}
    log = si_imu_log(arr[:, stamp_col], arr[:, 1:4], arr[:, 4:7], temp, meta, path)
    log.warnings.extend(warnings)
    return log
