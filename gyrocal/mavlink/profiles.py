"""Each autopilot's gyro thermal compensation, as parameters: names, units, sign, reference, range.

Our set is a per-axis polynomial in absolute temperature, ``Q(T) = c0 + c1 T + c2 T^2 + c3 T^3``
[deg/s, T in degC], meaning "the unit subtracts Q(T) from its output". A profile converts exactly
between Q and the autopilot's parameters, in both directions:

- ``to_params(Q, ctx, tmin, tmax)``: the parameter values that make the autopilot subtract Q(T)
  for T in [tmin, tmax] (the range the data covered; the autopilot clamps T into it);
- ``applied(params)``: the Q the autopilot subtracts now, as read back (with compensation off it is
  only the plain offset), so the daemon's ``raw = out + Q(T)`` holds;
- ``clamp_adjust(params, T)``: what the autopilot really subtracts minus Q(T); zero inside
  [TMIN, TMAX], and the link adds it to each sample so that the daemon's reconstruction stays exact
  outside that range too.

Frames: Q is in the BODY frame (the IMU messages' frame, where the daemon learns it); both autopilots
hold and subtract their offsets in the SENSOR (board) frame and rotate the result into the body frame
afterwards (``body = R @ (sensor - offset_sensor)``, R from the board rotation parameters,
gyrocal/mavlink/rotation.py). So ``to_params`` writes ``R.T @ Q`` and ``applied`` returns
``R @ offset_sensor``, power by power; ``sensor_q`` gives the sensor-frame polynomial unrotated.

Sources (docs/mavlink.md has the detail):

- PX4: src/modules/temperature_compensation/TemperatureCompensation.cpp (``calc_thermal_offsets_3D``:
  offset = X0 + X1 d + X2 d^2 + X3 d^3, d = clip(T, TMIN, TMAX) - TREF, rad/s) and
  src/lib/sensor_calibration/Gyroscope.hpp (``Correct``: R * (data - thermal_offset - CAL_GYROn_OFF)).
- ArduPilot: libraries/AP_InertialSensor/AP_InertialSensor_tempcal.cpp (``polynomial_eval``:
  (c1 d + c2 d^2 + c3 d^3) * 1e-6, d = clamp(T) - 35; ``correct_sensor``: v -= P(T - 35) - P(Tcal - 35))
  and AP_InertialSensor_Backend.cpp (``_rotate_and_correct_gyro``: tcal first, then ``-= gyro offset``).
"""

from __future__ import annotations

import struct
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from gyrocal.mavlink.poly import DEG_PER_RAD, shift
from gyrocal.mavlink.rotation import RotationError, ardupilot_board_matrix, px4_board_matrix

REAL32, INT8, INT32 = 9, 2, 6
"""MAV_PARAM_TYPE values used here."""
AXES = "XYZ"


def f32(value: float) -> float:
    """A value as the autopilot stores it (IEEE float32), back as a Python float."""
    return float(np.float32(value))


def encode_param(value: float, ptype: int, bytewise: bool) -> float:
    """The PARAM_SET/PARAM_VALUE float for a value of MAV_PARAM_TYPE ``ptype``.

    Integers travel bytewise (their bits reinterpreted as a float32) on PX4
    (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE) and cast to float on ArduPilot (C_CAST).
    A 24-bit device id would lose digits in a cast, so PX4's bytewise rule matters for TC_Gn_ID.
    """
    if ptype == REAL32 or not bytewise:
        return f32(value)
    fmt = {INT8: "<b3x", INT32: "<i"}[ptype]
    return struct.unpack("<f", struct.pack(fmt, int(value)))[0]


def decode_param(wire: float, ptype: int, bytewise: bool) -> float:
    """Inverse of :func:`encode_param`: the value a PARAM_VALUE carries."""
    if ptype == REAL32 or not bytewise:
        return f32(wire) if ptype == REAL32 else float(round(wire))
    raw = struct.pack("<f", wire)
    return float(struct.unpack("<b3x" if ptype == INT8 else "<i", raw)[0])


@dataclass(frozen=True)
class Param:
    name: str
    ptype: int = REAL32


class Profile(ABC):
    """One autopilot's gyro compensation for one IMU instance (0-based)."""

    name = "autopilot"
    own_boot_bias = False
    """Whether the autopilot re-measures the set's constant at each boot (a gyro calibration at rest)."""
    mav_autopilot = -1
    bytewise = False
    max_offset_dps = 11.0
    """Largest plausible offset over the range [deg/s] (0.2 rad/s, ArduPilot's INS_GYROFFS range)."""

    def __init__(self, instance: int = 0) -> None:
        if not 0 <= instance <= 2:
            raise ValueError(f"IMU instance {instance} must be 0, 1 or 2")
        self.instance = instance
        self.absent: set[str] = set()
        """Optional parameters (``optional``) this firmware did not answer: not asked for again."""

    optional: frozenset[str] = frozenset()
    """extra_context parameters some firmware lacks: unanswered, they are taken as absent, no fault."""

    @property
    @abstractmethod
    def enable(self) -> Param:
        """The switch: written 0 before the coefficients and 1 after they are verified."""

    @property
    @abstractmethod
    def coeffs(self) -> list[Param]:
        """The parameters a push writes while compensation is disabled."""

    @property
    @abstractmethod
    def context(self) -> list[Param]:
        """Parameters read before a push and at every read (offsets, ids, orientation)."""

    @property
    @abstractmethod
    def durable(self) -> list[str]:
        """Names that identify a pushed set across reboots (the autopilot never rewrites them itself)."""

    def all_params(self) -> list[Param]:
        return [self.enable, *self.coeffs, *self.context]

    def extra_context(self, p: Mapping[str, float]) -> list[Param]:
        """Parameters to read as well once ``p`` (a read of ``all_params``) is known: those that exist
        only in some configurations (ArduPilot's CUST_ROTn_* with a custom AHRS_ORIENTATION)."""
        return []

    @abstractmethod
    def rotation_names(self, p: Mapping[str, float]) -> list[str]:
        """The parameters that define the board rotation given ``p`` (compared before and after a push)."""

    @abstractmethod
    def board_matrix(self, p: Mapping[str, float]) -> np.ndarray:
        """R (3, 3): body = R @ sensor, from the board rotation parameters in ``p``.
        Raises :class:`~gyrocal.mavlink.rotation.RotationError` for a value it cannot map."""

    def rotation_of(self, p: Mapping[str, float]) -> dict[str, float]:
        """The board rotation parameters' values in ``p`` (recorded with a pushed set)."""
        return {k: float(p[k]) for k in self.rotation_names(p) if k in p}

    def _r(self, p: Mapping[str, float]) -> np.ndarray:
        try:
            return self.board_matrix(p)
        except RotationError:
            return np.eye(3)  # only reached for a read the link already refuses (problem())

    def sensor_q(self, q_body: np.ndarray, p: Mapping[str, float]) -> np.ndarray:
        """The sensor-frame polynomial the autopilot must hold to subtract ``q_body`` in the body frame."""
        return self.board_matrix(p).T @ np.asarray(q_body, dtype=np.float64)

    def rotation_problem(self, p: Mapping[str, float]) -> str | None:
        try:
            self.board_matrix(p)
        except RotationError as err:
            return (
                f"{err}; {self.name} applies its gyro offsets in the sensor frame and the IMU messages "
                "are in the body frame"
            )
        return None

    def types(self) -> dict[str, int]:
        return {p.name: p.ptype for p in self.all_params()}

    @abstractmethod
    def to_params(
        self, q_dps: np.ndarray, ctx: Mapping[str, float], tmin: float, tmax: float
    ) -> dict[str, float]:
        """Coefficient parameter values (float32) for Q (3, 4) [deg/s per degC^k]; see module docstring."""

    @abstractmethod
    def applied(self, p: Mapping[str, float]) -> np.ndarray:
        """The Q (3, 4) the autopilot subtracts with parameters ``p`` (a full read)."""

    @abstractmethod
    def clamp_adjust(self, p: Mapping[str, float], temp_c: np.ndarray) -> np.ndarray:
        """(N, 3) [deg/s]: actual subtraction minus ``applied(p)`` evaluated at temp_c."""

    def problem(self, p: Mapping[str, float]) -> str | None:
        """Why this autopilot's configuration cannot hold our set (None when it can)."""
        return None

    def needs_reboot(self, enable_at_boot: float | None) -> bool:
        """Whether a pushed set takes effect only after a reboot."""
        return False

    def is_enabled(self, p: Mapping[str, float]) -> bool:
        return p.get(self.enable.name) == 1.0

    def learning(self, p: Mapping[str, float]) -> bool:
        """The autopilot is learning its own temperature calibration (ArduPilot INS_TCALn_ENABLE = 2,
        a run its user started from a cold board): a push would end it unseen (an integrator's audit)."""
        return self.name == "ardupilot" and p.get(self.enable.name) == 2.0

    def check_range(self, q_dps: np.ndarray, tmin: float, tmax: float) -> str | None:
        """Refuse a set whose offset over [tmin, tmax] is beyond what a gyro offset can be."""
        if not np.all(np.isfinite(q_dps)):
            return "a coefficient is NaN or Inf"
        temps = np.linspace(tmin, tmax, 16)
        from gyrocal.mavlink.poly import evaluate

        peak = float(np.max(np.abs(evaluate(q_dps, temps))))
        if peak > self.max_offset_dps:
            return (
                f"offset reaches {peak:.3g} deg/s over {tmin:.1f}..{tmax:.1f} degC "
                f"(limit {self.max_offset_dps})"
            )
        return None


class Px4(Profile):
    """PX4: TC_G_ENABLE, TC_Gn_{ID,TREF,TMIN,TMAX,X0_0..X3_2} [rad/s per degC^k], CAL_GYROn_xOFF [rad/s]."""

    name = "px4"
    mav_autopilot = 12  # MAV_AUTOPILOT_PX4
    bytewise = True

    def __init__(self, instance: int = 0) -> None:
        super().__init__(instance)
        i = instance
        self.p_id, self.p_tref, self.p_tmin, self.p_tmax = (
            f"TC_G{i}_{s}" for s in ("ID", "TREF", "TMIN", "TMAX")
        )
        self.p_x = [[f"TC_G{i}_X{k}_{a}" for k in range(4)] for a in range(3)]
        self.p_cal_id = f"CAL_GYRO{i}_ID"
        self.p_cal_rot = f"CAL_GYRO{i}_ROT"
        self.optional = frozenset({self.p_cal_rot})
        self.p_cal_off = [f"CAL_GYRO{i}_{a}OFF" for a in AXES]

    @property
    def enable(self) -> Param:
        return Param("TC_G_ENABLE", INT32)

    @property
    def coeffs(self) -> list[Param]:
        out = [Param(self.p_id, INT32), Param(self.p_tref), Param(self.p_tmin), Param(self.p_tmax)]
        return out + [Param(n) for row in self.p_x for n in row]

    @property
    def context(self) -> list[Param]:
        return [
            Param(self.p_cal_id, INT32),
            *(Param(n) for n in self.p_cal_off),
            Param("SENS_BOARD_ROT", INT32),
            *(Param(n) for n in self.P_LEVEL),
        ]

    P_LEVEL = ("SENS_BOARD_X_OFF", "SENS_BOARD_Y_OFF", "SENS_BOARD_Z_OFF")
    """The board level adjustment [deg] (Euler roll, pitch, yaw) PX4 applies after SENS_BOARD_ROT."""

    def rotation_names(self, p: Mapping[str, float]) -> list[str]:
        return ["SENS_BOARD_ROT", *self.P_LEVEL]

    def board_matrix(self, p: Mapping[str, float]) -> np.ndarray:
        # Gyroscope::set_rotation: Dcmf(GetSensorLevelAdjustment()) * get_rot_matrix(GetBoardRotation())
        level = tuple(float(p.get(n, 0.0)) for n in self.P_LEVEL)
        return px4_board_matrix(float(p.get("SENS_BOARD_ROT", 0.0)), level)  # type: ignore[arg-type]

    @property
    def durable(self) -> list[str]:
        # the rotation is part of what a set means: a changed rotation is another (foreign) set
        return [
            self.enable.name, *(p.name for p in self.coeffs), *self.p_cal_off, "SENS_BOARD_ROT", *self.P_LEVEL
        ]

    def _caloff_rad(self, p: Mapping[str, float]) -> np.ndarray:
        return np.array([p.get(n, 0.0) for n in self.p_cal_off])

    def to_params(
        self, q_dps: np.ndarray, ctx: Mapping[str, float], tmin: float, tmax: float
    ) -> dict[str, float]:
        tref = round(tmin + tmax) / 2.0  # a half degree: exact in float32, central for conditioning
        a = shift(self.sensor_q(q_dps, ctx) / DEG_PER_RAD, tref)  # body -> sensor frame, then about TREF
        a[:, 0] -= self._caloff_rad(ctx)  # CAL_GYROn_xOFF is subtracted as well; it stays as it is
        out = {
            self.p_id: float(ctx.get(self.p_cal_id, 0.0)),
            self.p_tref: f32(tref),
            self.p_tmin: f32(tmin),
            self.p_tmax: f32(tmax),
        }
        for ax in range(3):
            for k in range(4):
                out[self.p_x[ax][k]] = f32(a[ax, k])
        return out

    def _thermal_on(self, p: Mapping[str, float]) -> bool:
        # the thermal offset applies only to the gyro whose device id matches TC_Gn_ID (set_sensor_id)
        return (
            self.is_enabled(p) and p.get(self.p_id) == p.get(self.p_cal_id) and p.get(self.p_id, 0.0) != 0.0
        )

    def _a(self, p: Mapping[str, float]) -> np.ndarray:
        return np.array([[p.get(self.p_x[ax][k], 0.0) for k in range(4)] for ax in range(3)])

    def applied(self, p: Mapping[str, float]) -> np.ndarray:
        a = self._a(p) if self._thermal_on(p) else np.zeros((3, 4))
        a[:, 0] += self._caloff_rad(p)
        tref = p.get(self.p_tref, 0.0) if self._thermal_on(p) else 0.0
        return self._r(p) @ shift(a, -tref) * DEG_PER_RAD  # sensor -> body frame

    def clamp_adjust(self, p: Mapping[str, float], temp_c: np.ndarray) -> np.ndarray:
        temp_c = np.asarray(temp_c, dtype=np.float64)
        if not self._thermal_on(p):
            return np.zeros((temp_c.size, 3))
        from gyrocal.mavlink.poly import evaluate

        a, tref = self._a(p), p[self.p_tref]
        d = temp_c - tref
        dc = np.clip(temp_c, p[self.p_tmin], p[self.p_tmax]) - tref
        return (evaluate(a, dc) - evaluate(a, d)) @ self._r(p).T * DEG_PER_RAD

    def extra_context(self, p: Mapping[str, float]) -> list[Param]:
        # CAL_GYROn_ROT: -1 for an internal gyro (SENS_BOARD_ROT applies), else an external gyro's own
        # rotation (PX4 1.12+; older firmware lacks it, so it is optional)
        return [] if self.p_cal_rot in self.absent else [Param(self.p_cal_rot, INT32)]

    def problem(self, p: Mapping[str, float]) -> str | None:
        why = self.rotation_problem(p)
        if why:
            return why
        rot = p.get(self.p_cal_rot)
        if rot is not None and rot >= 0:
            # an external gyro follows its own rotation, not SENS_BOARD_ROT: a set learnt and written
            # in the board frame was applied with x and y of the wrong sign, 1957/1379 deg/h left
            # against 1136/821 uncompensated, status saying "agree" (an integrator's audit)
            return (f"{self.p_cal_rot} = {rot:g}: an external gyro with its own rotation, which gyrocal does "
                    "not model (it writes TC_G in the board frame): refused, a set would be applied with "
                    "the wrong axes or signs (docs/mavlink.md, board rotation)")
        if not p.get(self.p_cal_id):
            return f"{self.p_cal_id} is 0: PX4 does not know this gyro's device id (run a gyro calibration)"
        return None

    def needs_reboot(self, enable_at_boot: float | None) -> bool:
        # TC_G_ENABLE is reboot_required (temp_comp_params_gyro.yaml); with it on at boot the module
        # reloads TC_Gn_* on every parameter update (TemperatureCompensationModule::Run)
        return enable_at_boot != 1.0


class ArduPilot(Profile):
    """ArduPilot: INS_TCALn_{ENABLE,TMIN,TMAX,GYR1..3_X..Z} [1e-6 rad/s per degC^k] about 35 degC."""

    name = "ardupilot"
    mav_autopilot = 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
    bytewise = False
    TREF_C = 35.0
    """TEMP_REFERENCE in AP_InertialSensor_tempcal.cpp."""
    SCALE = 1.0e6
    """SCALE_FACTOR in AP_InertialSensor_tempcal.cpp: parameters hold 1e6 x rad/s per degC^k."""

    def __init__(self, instance: int = 0) -> None:
        super().__init__(instance)
        n = instance + 1
        self.p_tmin, self.p_tmax = f"INS_TCAL{n}_TMIN", f"INS_TCAL{n}_TMAX"
        self.p_g = [[f"INS_TCAL{n}_GYR{k}_{a}" for k in (1, 2, 3)] for a in AXES]
        off = "INS_GYROFFS" if n == 1 else f"INS_GYR{n}OFFS"
        self.p_off = [f"{off}_{a}" for a in AXES]
        self.p_caltemp = f"INS_GYR{n}_CALTEMP"

    @property
    def enable(self) -> Param:
        return Param(f"INS_TCAL{self.instance + 1}_ENABLE", INT8)

    @property
    def coeffs(self) -> list[Param]:
        return [
            Param(self.p_tmin),
            Param(self.p_tmax),
            *(Param(x) for row in self.p_g for x in row),
            *(Param(x) for x in self.p_off),
        ]

    @property
    def context(self) -> list[Param]:
        return [Param(self.p_caltemp), Param("AHRS_ORIENTATION", INT8)]

    @staticmethod
    def _custom(p: Mapping[str, float]) -> list[str]:
        rot = p.get("AHRS_ORIENTATION", 0.0)
        if rot in (101.0, 102.0):  # ROTATION_CUSTOM_1/2: AP_CustomRotations, CUST_ROTn_{ROLL,PITCH,YAW} [deg]
            n = int(rot) - 100
            return [f"CUST_ROT{n}_ROLL", f"CUST_ROT{n}_PITCH", f"CUST_ROT{n}_YAW"]
        return []

    def extra_context(self, p: Mapping[str, float]) -> list[Param]:
        return [Param(n) for n in self._custom(p)]

    def rotation_names(self, p: Mapping[str, float]) -> list[str]:
        return ["AHRS_ORIENTATION", *self._custom(p)]

    def board_matrix(self, p: Mapping[str, float]) -> np.ndarray:
        # _rotate_and_correct_gyro: tcal, then -= gyro offset, then gyro.rotate(_board_orientation)
        names = self._custom(p)
        rpy = tuple(float(p[n]) for n in names) if names and all(n in p for n in names) else None
        return ardupilot_board_matrix(float(p.get("AHRS_ORIENTATION", 0.0)), rpy)  # type: ignore[arg-type]

    own_boot_bias = True  # INS_GYR_CAL=1, ArduPilot's default: INS_GYROFFS and CALTEMP at each boot

    @property
    def durable(self) -> list[str]:
        # INS_GYROFFS and CALTEMP are re-measured at each boot's gyro calibration (INS_GYR_CAL=1); the
        # rotation is part of what a set means (a changed rotation makes it a foreign set)
        return [self.enable.name, self.p_tmin, self.p_tmax, *(x for row in self.p_g for x in row),
                "AHRS_ORIENTATION"]

    def _tcal(self, p: Mapping[str, float], tmin: float, tmax: float) -> float:
        return float(np.clip(p.get(self.p_caltemp, -300.0), tmin, tmax))

    def _poly(self, g: np.ndarray, d: np.ndarray) -> np.ndarray:
        """P(d) per axis, (N, 3) [rad/s]; g (3, 3) holds the 1e-6-scaled coefficients of d, d^2, d^3."""
        d = np.asarray(d, dtype=np.float64)[:, None]
        return (g[:, 0] * d + g[:, 1] * d**2 + g[:, 2] * d**3) / self.SCALE

    def _g(self, p: Mapping[str, float]) -> np.ndarray:
        return np.array([[p.get(x, 0.0) for x in row] for row in self.p_g])

    def to_params(
        self, q_dps: np.ndarray, ctx: Mapping[str, float], tmin: float, tmax: float
    ) -> dict[str, float]:
        a = shift(self.sensor_q(q_dps, ctx) / DEG_PER_RAD, self.TREF_C)  # body -> sensor frame, about 35
        g = np.array([[f32(v) for v in row] for row in a[:, 1:] * self.SCALE])
        tmin32, tmax32 = f32(tmin), f32(tmax)
        # the constant goes to INS_GYROFFS: offset = GYROFFS + P(T-35) - P(Tcal-35) must equal a0 + P(T-35)
        off = a[:, 0] + self._poly(g, np.array([self._tcal(ctx, tmin32, tmax32) - self.TREF_C]))[0]
        out = {self.p_tmin: tmin32, self.p_tmax: tmax32}
        for ax in range(3):
            for k in range(3):
                out[self.p_g[ax][k]] = float(g[ax, k])
            out[self.p_off[ax]] = f32(off[ax])
        return out

    def applied(self, p: Mapping[str, float]) -> np.ndarray:
        off = np.array([p.get(x, 0.0) for x in self.p_off])
        a = np.zeros((3, 4))
        if self.is_enabled(p):
            g = self._g(p)
            a[:, 1:] = g / self.SCALE
            tcal = self._tcal(p, p[self.p_tmin], p[self.p_tmax])
            off = off - self._poly(g, np.array([tcal - self.TREF_C]))[0]
        a[:, 0] = off
        return self._r(p) @ shift(a, -self.TREF_C) * DEG_PER_RAD  # sensor -> body frame

    def clamp_adjust(self, p: Mapping[str, float], temp_c: np.ndarray) -> np.ndarray:
        temp_c = np.asarray(temp_c, dtype=np.float64)
        if not self.is_enabled(p):
            return np.zeros((temp_c.size, 3))
        g = self._g(p)
        tc = np.clip(temp_c, p[self.p_tmin], p[self.p_tmax])
        diff = self._poly(g, tc - self.TREF_C) - self._poly(g, temp_c - self.TREF_C)
        return diff @ self._r(p).T * DEG_PER_RAD

    def problem(self, p: Mapping[str, float]) -> str | None:
        return self.rotation_problem(p)


PROFILES: dict[str, type[Profile]] = {"px4": Px4, "ardupilot": ArduPilot}
BY_MAV_AUTOPILOT = {cls.mav_autopilot: name for name, cls in PROFILES.items()}
