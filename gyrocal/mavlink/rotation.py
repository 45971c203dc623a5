"""Board rotations of PX4 and ArduPilot: the enum value of SENS_BOARD_ROT / AHRS_ORIENTATION as a matrix.

Why: both autopilots subtract their gyro offsets (PX4 TC_G*/CAL_GYRO*, ArduPilot INS_TCAL*/INS_GYROFFS)
in the SENSOR (board) frame and then rotate into the BODY frame, while the IMU messages the daemon
learns from are in the body frame. ``R`` below is that rotation: ``body = R @ sensor``. The pushed
offset therefore is ``offset_sensor = R.T @ offset_body`` (R is orthonormal), power by power.

Both autopilots number the rotations alike (the MAVLink MAV_SENSOR_ORIENTATION list), each entry a
roll, then pitch, then yaw (Euler 3-2-1: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``):

- PX4 ``src/lib/conversion/rotation.h`` (PX4/PX4-Autopilot 019b565433800f9b56cd0fb51dc93777c3a79d56):
  ``rot_lookup[]`` holds {roll, pitch, yaw} in whole degrees per enum value 0..47, and
  ``rotation.cpp`` ``get_rot_matrix`` returns ``Dcmf{Eulerf{roll, pitch, yaw}}``. The sensor
  calibration (``src/lib/sensor_calibration/Gyroscope.cpp`` ``set_rotation``) applies
  ``Dcmf(GetSensorLevelAdjustment()) * get_rot_matrix(SENS_BOARD_ROT)`` where the level adjustment is
  the Euler angles SENS_BOARD_X_OFF, Y_OFF, Z_OFF [deg] (``Utilities.cpp``). An older PX4 (e.g. commit
  d41208735daba6c70bca84757730386172a0b301, before it followed the MAVLink list) numbered 26..41
  differently; this table is the MAVLink-aligned one.
- ArduPilot ``libraries/AP_Math/rotations.h`` (ArduPilot/ardupilot 17bcf9310c23a3b7a2ad51b8d12537058c6424c2)
  names 0..43 the same way; ``vector3.cpp`` ``Vector3<T>::rotate`` (0..38 at commit
  0a7bb2df0f00fe8da98cc42100a75f2ee9a7bd29; 39..43 in a later version) applies each by component
  swaps (roll first, then pitch, then yaw). Entry 38 (ROTATION_ROLL_90_PITCH_68_YAW_293) is an
  explicit matrix there (0.143039f, ...), which we take as written with its later 30-digit constants
  (equal to 1e-6); PX4's entry 38 is {90, 68, 293} whole degrees,
  so the two differ by under a degree. 41..43 differ between the two (PX4: ROLL_270_YAW_180,
  ROLL_270_YAW_270, PITCH_90_YAW_180, ...; ArduPilot: PITCH_7, ROLL_45, ROLL_315).
- ArduPilot ROTATION_CUSTOM_1/2 (101/102): ``AP_CustomRotations.cpp``: ``m.from_euler(CUST_ROTn_ROLL,
  CUST_ROTn_PITCH, CUST_ROTn_YAW)`` [deg, "euler 321 (yaw, pitch, roll) ordering"], ``v = m * v``.
  ROTATION_CUSTOM_OLD (100) is converted to 101 at boot since Nov 2021 (``AP_AHRS::init``); a
  firmware that still holds 100 reads AHRS_CUSTOM_ROLL/PIT/YAW, which this module does not map.
"""

from __future__ import annotations

import numpy as np

PX4_EULER_DEG: tuple[tuple[float, float, float], ...] = (
    (0, 0, 0), (0, 0, 45), (0, 0, 90), (0, 0, 135), (0, 0, 180), (0, 0, 225), (0, 0, 270), (0, 0, 315),
    (180, 0, 0), (180, 0, 45), (180, 0, 90), (180, 0, 135), (0, 180, 0), (180, 0, 225), (180, 0, 270),
    (180, 0, 315), (90, 0, 0), (90, 0, 45), (90, 0, 90), (90, 0, 135), (270, 0, 0), (270, 0, 45),
    (270, 0, 90), (270, 0, 135), (0, 90, 0), (0, 270, 0), (0, 180, 90), (0, 180, 270), (90, 90, 0),
    (180, 90, 0), (270, 90, 0), (90, 180, 0), (270, 180, 0), (90, 270, 0), (180, 270, 0), (270, 270, 0),
    (90, 180, 90), (90, 0, 270), (90, 68, 293), (0, 315, 0), (90, 315, 0), (270, 0, 180), (270, 0, 270),
    (0, 90, 180), (0, 9, 180), (0, 45, 0), (270, 0, 225), (270, 0, 315),
)
"""PX4 rot_lookup[] {roll, pitch, yaw} [deg], index = SENS_BOARD_ROT (rotation.h, 0..47)."""

ARDUPILOT_EULER_DEG: tuple[tuple[float, float, float] | None, ...] = (
    *PX4_EULER_DEG[:38], None, (0, 315, 0), (90, 315, 0), (0, 7, 0), (45, 0, 0), (315, 0, 0),
)
"""ArduPilot Rotation 0..43 as {roll, pitch, yaw} [deg], read from the enum names in rotations.h
(ROTATION_ROLL_90_YAW_45 = roll 90 then yaw 45). 38 is the explicit matrix below."""

ARDUPILOT_ROT38 = np.array(
    [
        [0.14303897231223747232853327, 0.36877648650320382639478111, -0.91844638134308709265241077],
        [-0.33213277779664740485543461, -0.85628942146641884303193137, -0.39554550256296522325882847],
        [-0.93232380121551217122544130, 0.36162457008209242248497616, 0.0],
    ]
)
"""ArduPilot ROTATION_ROLL_90_PITCH_68_YAW_293 as written in vector3.cpp (rows: x', y', z')."""

CUSTOM_OLD, CUSTOM_1, CUSTOM_2 = 100, 101, 102
"""ArduPilot's custom rotations (rotations.h)."""


class RotationError(ValueError):
    """An orientation value this module cannot turn into a matrix; the message names parameter,
    value and why (the link refuses to push then, as one clear error)."""


def euler_321(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` [angles in deg]: PX4 ``Dcm(Euler)``, ArduPilot
    ``Matrix3::from_euler``; maps the board (sensor) frame to the body frame."""
    r, p, y = np.radians([roll_deg, pitch_deg, yaw_deg])
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    m = np.array(
        [
            [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
            [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
            [-sp, sr * cp, cr * cp],
        ]
    )
    m[np.abs(m) < 1e-15] = 0.0  # exact zeros for the right-angle entries
    return m


def px4_board_matrix(rot: float, level_off_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
                     param: str = "SENS_BOARD_ROT") -> np.ndarray:
    """PX4's board rotation: ``Dcm(Euler(SENS_BOARD_X/Y/Z_OFF)) @ get_rot_matrix(SENS_BOARD_ROT)``."""
    if rot != int(rot) or not 0 <= int(rot) < len(PX4_EULER_DEG):
        raise RotationError(
            f"{param} = {rot:g}: PX4 defines 0..{len(PX4_EULER_DEG) - 1} (src/lib/conversion/rotation.h); "
            "gyrocal cannot rotate coefficients for another value"
        )
    if not all(np.isfinite(level_off_deg)):
        raise RotationError(f"SENS_BOARD_X/Y/Z_OFF = {level_off_deg}: not finite")
    return euler_321(*level_off_deg) @ euler_321(*PX4_EULER_DEG[int(rot)])


def ardupilot_board_matrix(rot: float, custom_rpy_deg: tuple[float, float, float] | None = None,
                           param: str = "AHRS_ORIENTATION") -> np.ndarray:
    """ArduPilot's board rotation for AHRS_ORIENTATION ``rot``; 101/102 need CUST_ROTn_ROLL/PITCH/YAW."""
    if rot in (CUSTOM_1, CUSTOM_2):
        if custom_rpy_deg is None or not all(np.isfinite(custom_rpy_deg)):
            raise RotationError(
                f"{param} = {rot:g} (ROTATION_CUSTOM_{int(rot) - 100}): its CUST_ROT{int(rot) - 100}_ROLL/"
                "PITCH/YAW could not be read (CUST_ROT_ENABLE = 0?); gyrocal cannot rotate coefficients"
            )
        return euler_321(*custom_rpy_deg)
    if rot == CUSTOM_OLD:
        raise RotationError(
            f"{param} = 100 (ROTATION_CUSTOM_OLD): ArduPilot converts it to 101 with CUST_ROT1_* at boot "
            "since Nov 2021; a firmware that still holds 100 uses AHRS_CUSTOM_ROLL/PIT/YAW, which gyrocal "
            "does not read. Update the firmware or set 101 and CUST_ROT1_*"
        )
    if rot != int(rot) or not 0 <= int(rot) < len(ARDUPILOT_EULER_DEG):
        raise RotationError(
            f"{param} = {rot:g}: ArduPilot defines 0..{len(ARDUPILOT_EULER_DEG) - 1} and 100..102 "
            "(libraries/AP_Math/rotations.h); gyrocal cannot rotate coefficients for another value"
        )
    euler = ARDUPILOT_EULER_DEG[int(rot)]
    return ARDUPILOT_ROT38.copy() if euler is None else euler_321(*euler)


def rotate_poly(r: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Coefficients (3, K) of ``r @ Q(T)`` for Q (3, K): each power's vector rotated alike."""
    return np.asarray(r, dtype=np.float64) @ np.asarray(q, dtype=np.float64)
