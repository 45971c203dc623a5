"""The virtual autopilot's board rotation, transcribed from ArduPilot's ``Vector3<T>::rotate``.

Why a second implementation: gyrocal/mavlink/rotation.py builds each matrix from Euler angles (PX4's
rot_lookup table, ArduPilot's enum names). The virtual autopilot must not share that code, or a wrong
table entry would be wrong on both sides and still "calibrate". This module follows the other
definition in the sources, ArduPilot ``libraries/AP_Math/vector3.cpp`` ``Vector3<T>::rotate``: a
sequence of component swaps per enum value (roll first, then pitch, then yaw), written out here
statement by statement. PX4 numbers these values alike (rotation.h, the MAVLink
MAV_SENSOR_ORIENTATION list), so the same function serves the virtual PX4.

Covered: 0..37, 39 and 40 (component swaps and 45-degree steps). Not covered (ValueError): 38 (an
explicit, slightly different matrix in each autopilot) and 41 and above (PX4 and ArduPilot differ).
"""

from __future__ import annotations

import numpy as np

H = 0.70710678118654757
"""HALF_SQRT_2 in vector3.cpp."""

SUPPORTED = (*range(38), 39, 40)


def _roll_90(x, y, z):  # tmp = z; z = y; y = -tmp;
    return x, -z, y


def _roll_270(x, y, z):  # tmp = z; z = -y; y = tmp;
    return x, z, -y


def _roll_180(x, y, z):
    return x, -y, -z


def _pitch_90(x, y, z):  # tmp = z; z = -x; x = tmp;
    return z, y, -x


def _pitch_270(x, y, z):  # tmp = z; z = x; x = -tmp;
    return -z, y, x


def _pitch_180(x, y, z):
    return -x, y, -z


def _pitch_315(x, y, z):  # tmp = H*(x - z); z = H*(x + z); x = tmp;
    return H * (x - z), y, H * (x + z)


def _yaw(deg: int):
    def f(x, y, z):
        if deg == 0:
            return x, y, z
        if deg == 45:
            return H * (x - y), H * (x + y), z
        if deg == 90:
            return -y, x, z
        if deg == 135:
            return -H * (x + y), H * (x - y), z
        if deg == 180:
            return -x, -y, z
        if deg == 225:
            return H * (y - x), -H * (x + y), z
        if deg == 270:
            return y, -x, z
        if deg == 315:
            return H * (x + y), H * (y - x), z
        raise AssertionError(deg)

    return f


def _then(*steps):
    def f(x, y, z):
        for s in steps:
            x, y, z = s(x, y, z)
        return x, y, z

    return f


def _roll_180_yaw(deg: int):
    # vector3.cpp writes ROLL_180_YAW_n as one expression; it equals roll 180 then yaw n
    return _then(_roll_180, _yaw(deg))


STEPS = {
    **{i: _yaw(45 * i) for i in range(8)},  # 0..7: NONE, YAW_45 .. YAW_315
    8: _roll_180,
    9: _roll_180_yaw(45),  # tmp = H*(x + y); y = H*(x - y); x = tmp; z = -z;
    10: _roll_180_yaw(90),  # tmp = x; x = y; y = tmp; z = -z;
    11: _roll_180_yaw(135),  # tmp = H*(y - x); y = H*(y + x); x = tmp; z = -z;
    12: _pitch_180,  # x = -x; z = -z;
    13: _roll_180_yaw(225),  # tmp = -H*(x + y); y = H*(y - x); x = tmp; z = -z;
    14: _roll_180_yaw(270),  # tmp = x; x = -y; y = -tmp; z = -z;
    15: _roll_180_yaw(315),  # tmp = H*(x - y); y = -H*(x + y); x = tmp; z = -z;
    16: _roll_90,
    17: _then(_roll_90, _yaw(45)),
    18: _then(_roll_90, _yaw(90)),
    19: _then(_roll_90, _yaw(135)),
    20: _roll_270,
    21: _then(_roll_270, _yaw(45)),
    22: _then(_roll_270, _yaw(90)),
    23: _then(_roll_270, _yaw(135)),
    24: _pitch_90,
    25: _pitch_270,
    26: _then(lambda x, y, z: (x, y, -z), lambda x, y, z: (-y, -x, z)),  # z = -z; tmp = -x; x = -y; y = tmp;
    27: _then(_pitch_180, _yaw(270)),  # x = -x; z = -z; tmp = x; x = y; y = -tmp;
    28: _then(_roll_90, _pitch_90),
    29: _then(_roll_180, _pitch_90),
    30: _then(_roll_270, _pitch_90),
    31: _then(_roll_90, _pitch_180),
    32: _then(_roll_270, _pitch_180),
    33: _then(_roll_90, _pitch_270),
    34: _then(_roll_180, _pitch_270),
    35: _then(_roll_270, _pitch_270),
    36: _then(_roll_90, _pitch_180, _yaw(90)),
    37: _then(_roll_90, _yaw(270)),
    39: _pitch_315,
    40: _then(_roll_90, _pitch_315),
}


def rotate(rot: int, v: np.ndarray) -> np.ndarray:
    """``v`` (..., 3) in the board (sensor) frame -> body frame, as the autopilot rotates it."""
    if int(rot) not in STEPS:
        raise ValueError(f"the virtual autopilot models board rotations {SUPPORTED}, not {rot}")
    v = np.asarray(v, dtype=np.float64)
    x, y, z = STEPS[int(rot)](v[..., 0], v[..., 1], v[..., 2])
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)
