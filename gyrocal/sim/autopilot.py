"""A virtual PX4 or ArduPilot autopilot: the parts of it gyrocal talks to, with each one's semantics.

Pure logic, no I/O: ``power_on()`` starts a boot, ``render(t_s)`` returns the MAVLink messages due
up to unit time t_s (IMU stream, heartbeat, temperature message), ``handle(msg)`` answers a host
message (PARAM_SET / PARAM_REQUEST_READ -> PARAM_VALUE, COMMAND_LONG -> COMMAND_ACK and its effect).
gyrocal/sim/autopilot_run.py carries the bytes over a pty or UDP.

The gyro: raw = switch-on bias (new at each boot, truth.TruthModel) + a cubic in temperature
(``thermal_dps``, fixed per seed) + white noise, while the board warms from 20 to 50 degC
(truth.Thermal; ``ambients_c`` starts each boot of a run at its own temperature, rising 30 degC).
The output subtracts what the autopilot's own parameters say, as the real code does
(see gyrocal/mavlink/profiles.py and docs/mavlink.md for the sources):

- PX4: HIGHRES_IMU [rad/s] = raw - thermal offset - CAL_GYRO0_xOFF. The thermal offset is
  evaluated at the temperature of its last publication, republished when the temperature moved by
  more than 1 degC or the parameters changed (TemperatureCompensation::update_offsets_gyro), only if
  TC_G_ENABLE was 1 at boot (TC_G_ENABLE is reboot_required) and TC_G0_ID matches the gyro. With
  TC_G_ENABLE set to 0 at run time, the last published offset stays (it is no longer updated).
  The EKF2 bias that the real HIGHRES_IMU also subtracts is not modelled (zero).
- ArduPilot: RAW_IMU [mrad/s, int16, truncated toward zero as C does] = raw - (P(T-35) - P(Tcal-35))
  (only while INS_TCAL1_ENABLE = 1, read live) - INS_GYROFFS; at each boot a gyro calibration sets
  INS_GYROFFS to the mean raw rate and INS_GYR1_CALTEMP to the temperature then (INS_GYR_CAL = 1).

Frames: the raw offset, the compensation and the boot gyro calibration live in the SENSOR (board)
frame, and the output is rotated into the BODY frame by the board rotation parameter (PX4
SENS_BOARD_ROT, ArduPilot AHRS_ORIENTATION; ``rotation=``) as both autopilots do after subtracting
their offsets (PX4 ``Gyroscope::Correct``, ArduPilot ``_rotate_and_correct_gyro``). The rotation is
gyrocal/sim/board_rotation.py, a transcription of ArduPilot's ``Vector3::rotate``, independent of the
link's gyrocal/mavlink/rotation.py. The accelerometer reads a level vehicle at rest (body frame).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gyrocal.mavlink import pymav
from gyrocal.mavlink.profiles import INT8, INT32, REAL32, ArduPilot, Px4, decode_param, encode_param, f32
from gyrocal.sim import board_rotation
from gyrocal.sim.truth import Thermal, TruthModel

G0 = 9.80665
RAD = math.pi / 180.0


@dataclass
class AutopilotFaults:
    """Injected faults: drop the next N PARAM_VALUE answers to PARAM_SET; refuse writes of one parameter
    (the echo carries the value kept); reboot after the N-th PARAM_SET (0 = never); go silent after
    the N-th PARAM_SET, unanswered, for ``silence_s`` [s], then go on in the same boot (0 = never);
    send every IMU temperature as 0 ("not provided"); after the N-th PARAM_SET, apply every write but
    answer no parameter message for ``silence_s`` (a downlink that loses them), the stream going on."""

    drop_param_values: int = 0
    reject_param: str = ""
    reboot_after_sets: int = 0
    silence_after_sets: int = 0
    silence_s: float = 5.0
    no_temperature: bool = False  # the IMU messages' temperature 0: "not provided" (common.xml)
    mute_params_after_sets: int = 0  # after the N-th PARAM_SET, no PARAM_VALUE for silence_s [s]


def default_thermal_dps(seed: int) -> np.ndarray:
    """The true offset polynomial Q(T) (3, 4) [deg/s per degC^k], about 0 degC, fixed per seed.

    Built from values at 20, 35 and 50 degC of about 0.05-0.3 deg/s (a consumer MEMS gyro over its
    warm-up: 180-1100 deg/h), plus a small cubic.
    """
    rng = np.random.default_rng([seed, 0x7E4])
    q = np.zeros((3, 4))
    for ax in range(3):
        d = np.array([20.0, 35.0, 50.0])
        v = rng.uniform(-0.3, 0.3, 3)
        a2, a1, a0 = np.polyfit(d, v, 2)
        q[ax, :3] = (a0, a1, a2)
        q[ax, 3] = rng.uniform(-2e-6, 2e-6)
    return q


@dataclass
class BootState:
    index: int
    t0_wall: float = 0.0
    bias_dps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tc_running: bool = False
    thermal_pub_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    t_pub_c: float | None = None
    next_tc_poll_s: float = 0.0
    sample_index: int = 0
    next_hb_s: float = 0.0
    next_temp_s: float = 0.0


class VirtualAutopilot:
    """One autopilot with one gyro. ``kind``: "px4" or "ardupilot". ``rate_hz``: IMU output rate."""

    def __init__(
        self,
        kind: str,
        rate_hz: float = 250.0,
        seed: int = 0,
        *,
        truth: TruthModel | None = None,
        thermal: Thermal | None = None,
        faults: AutopilotFaults | None = None,
        sysid: int = 1,
        noise_dps: float = 0.05,
        rotation: int = 0,
        ambients_c: tuple[float, ...] = (),
    ) -> None:
        if kind not in ("px4", "ardupilot"):
            raise ValueError(f"autopilot {kind!r}: px4 or ardupilot")
        self.kind, self.rate_hz, self.seed, self.sysid = kind, float(rate_hz), int(seed), sysid
        self.profile = Px4(0) if kind == "px4" else ArduPilot(0)
        self.truth = truth or TruthModel()
        self.thermal = thermal or Thermal(ambient_c=20.0, rise_c=30.0, tau_s=120.0)
        self.ambients_c = tuple(float(a) for a in ambients_c)
        """[degC] The board's temperature at each boot of this run, in order (the last repeats; empty:
        the thermal model's own ambient): a warm-up on a hotter day, to widen the range seen."""
        self._boots_here = 0
        self.noise_dps = noise_dps
        """White gyro noise at the stream rate [deg/s]: a MEMS gyro after the autopilot's low-pass filter."""
        self.q_true = default_thermal_dps(seed)
        self.faults = faults or AutopilotFaults()
        self.mav = pymav.codec(sysid, 1)
        self.d = pymav.dialect()
        self.params, self.ptypes = self._defaults()
        board_rotation.rotate(rotation, np.zeros(3))  # refuse a rotation it does not model, up front
        self.params[self.rotation_param] = float(rotation)
        self.order = list(self.params)
        self.boot = BootState(0)
        self.boot_count = 0
        self.streams: dict[int, float] = {}  # message id -> interval [s]
        self.stream_next: dict[int, float] = {}
        self.sets_seen = 0
        self.reboot_pending = False
        self.silence_pending = False  # AutopilotFaults.silence_after_sets: the runner stops sending
        self._params_muted_until = -1.0  # unit time [s] until which no PARAM_VALUE is sent
        self.uid = int(np.random.default_rng([seed, 0x51D]).integers(1, 2**63))
        self._rng = np.random.default_rng([seed, 0xA7])

    # -- parameters ---------------------------------------------------------------------------
    @property
    def rotation_param(self) -> str:
        return "SENS_BOARD_ROT" if self.kind == "px4" else "AHRS_ORIENTATION"

    def to_body(self, v_sensor: np.ndarray) -> np.ndarray:
        """Sensor (board) frame -> body frame with the board rotation the autopilot holds now."""
        return board_rotation.rotate(int(self.params[self.rotation_param]), v_sensor)

    def _defaults(self) -> tuple[dict[str, float], dict[str, int]]:
        p = self.profile
        vals: dict[str, float] = {}
        types: dict[str, int] = {}
        for prm in p.all_params():
            vals[prm.name] = 0.0
            types[prm.name] = prm.ptype
        if self.kind == "px4":
            vals.update(
                {"TC_G0_TREF": 25.0, "TC_G0_TMIN": 0.0, "TC_G0_TMAX": 100.0, "CAL_GYRO0_ID": 2490378.0}
            )
            rng = np.random.default_rng([self.seed, 0xCA1])
            for ax in "XYZ":  # a gyro calibration done once at the factory [rad/s]
                vals[f"CAL_GYRO0_{ax}OFF"] = f32(rng.normal(0.0, 0.002))
            vals["CAL_GYRO0_ROT"], types["CAL_GYRO0_ROT"] = -1.0, INT32  # internal: SENS_BOARD_ROT applies
        else:
            vals.update({"INS_TCAL1_TMAX": 70.0, "INS_GYR1_CALTEMP": -300.0})
            vals["INS_GYR_CAL"], types["INS_GYR_CAL"] = 1.0, INT8
        vals["SYSID_THISMAV" if self.kind == "ardupilot" else "MAV_SYS_ID"] = float(self.sysid)
        types["SYSID_THISMAV" if self.kind == "ardupilot" else "MAV_SYS_ID"] = (
            INT32 if self.kind == "px4" else INT8
        )
        return vals, types

    def flash_state(self) -> dict[str, Any]:
        return {"params": dict(self.params), "boot_count": self.boot_count}

    def load_flash(self, state: dict[str, Any]) -> None:
        self.params.update({k: float(v) for k, v in state.get("params", {}).items() if k in self.params})
        self.boot_count = int(state.get("boot_count", 0))

    # -- boot and physics -----------------------------------------------------------------------
    def power_on(self, wall_s: float = 0.0) -> None:
        """A new boot: fresh bias, time from 0, streams off, each autopilot's boot-time behaviour."""
        self.boot_count += 1
        self.thermal = self.thermal.at_boot(self.ambients_c, self._boots_here)
        self._boots_here += 1
        b = BootState(self.boot_count, t0_wall=wall_s)
        b.bias_dps = self.truth.switch_on_bias(self.seed, self.boot_count)
        self.boot = b
        self.streams, self.stream_next = {}, {}
        self.sets_seen = 0
        self.reboot_pending = False
        temp0 = float(self.thermal.temp_c(np.array([0.0]))[0])
        if self.kind == "px4":
            b.tc_running = self.params["TC_G_ENABLE"] == 1.0
        elif self.params.get("INS_GYR_CAL") == 1.0:
            # the boot gyro calibration averages the raw rate (tcal and offsets are not applied then)
            raw = self.raw_offset_dps(np.array([temp0]))[0] + self._rng.normal(0, self.noise_dps / 30, 3)
            for ax, v in zip("XYZ", raw, strict=True):
                self.params[f"INS_GYROFFS_{ax}"] = f32(v * RAD)
            self.params["INS_GYR1_CALTEMP"] = f32(temp0)

    def raw_offset_dps(self, temp_c: np.ndarray) -> np.ndarray:
        """The true gyro offset of this boot at temp_c, (N, 3) [deg/s], in the SENSOR frame: switch-on
        bias + Q(T), no noise."""
        from gyrocal.mavlink.poly import evaluate

        return evaluate(self.q_true, temp_c) + self.boot.bias_dps

    def temp_c(self, t_s: float) -> float:
        return float(self.thermal.temp_c(np.array([t_s]))[0])

    def _px4_poll(self, t_s: float, temp: float, force: bool = False) -> None:
        """temperature_compensation at 1 Hz: republish the offset when T moved > 1 degC or params changed."""
        b = self.boot
        if not b.tc_running or (t_s < b.next_tc_poll_s and not force):
            return
        b.next_tc_poll_s = t_s + 1.0
        p = self.params
        if p["TC_G_ENABLE"] != 1.0 or p["TC_G0_ID"] != p["CAL_GYRO0_ID"]:
            return
        if b.t_pub_c is None or abs(temp - b.t_pub_c) > 1.0 or force:
            d = min(max(temp, p["TC_G0_TMIN"]), p["TC_G0_TMAX"]) - p["TC_G0_TREF"]
            b.thermal_pub_rad = np.array(
                [sum(p[f"TC_G0_X{k}_{a}"] * d**k for k in range(4)) for a in range(3)]
            )
            b.t_pub_c = temp

    def compensation_dps(self, temp_c: float) -> np.ndarray:
        """What the autopilot subtracts now at temp_c [deg/s], in the SENSOR frame."""
        p = self.params
        if self.kind == "px4":
            return (self.boot.thermal_pub_rad + np.array([p[f"CAL_GYRO0_{a}OFF"] for a in "XYZ"])) / RAD
        corr = np.zeros(3)
        if p["INS_TCAL1_ENABLE"] == 1.0:
            prof: ArduPilot = self.profile  # type: ignore[assignment]
            g = prof._g(p)
            tc = min(max(temp_c, p["INS_TCAL1_TMIN"]), p["INS_TCAL1_TMAX"])
            tcal = min(max(p["INS_GYR1_CALTEMP"], p["INS_TCAL1_TMIN"]), p["INS_TCAL1_TMAX"])
            corr = (prof._poly(g, np.array([tc - 35.0])) - prof._poly(g, np.array([tcal - 35.0])))[0]
        return (corr + np.array([p[f"INS_GYROFFS_{a}"] for a in "XYZ"])) / RAD

    def offset_error_dps(self, temp_c: float) -> np.ndarray:
        """True offset left in the output at temp_c [deg/s], BODY frame: raw offset minus what is
        subtracted, rotated as the output is."""
        return self.to_body(self.raw_offset_dps(np.array([temp_c]))[0] - self.compensation_dps(temp_c))

    def render(self, t_s: float) -> list[Any]:
        """All messages due up to unit time t_s [s since boot], in time order."""
        out: list[Any] = []
        b, d, mav = self.boot, self.d, self.mav
        dt = 1.0 / self.rate_hz
        while b.next_hb_s <= t_s:
            out.append(d.MAVLink_heartbeat_message(2, self.profile.mav_autopilot, 1, 0, 3, 3))
            b.next_hb_s += 1.0
        while (b.sample_index + 1) * dt <= t_s:
            b.sample_index += 1
            ts = b.sample_index * dt
            temp = self.temp_c(ts)
            if self.kind == "px4":
                self._px4_poll(ts, temp)
            for mid, interval in self.streams.items():
                if ts + 1e-9 >= self.stream_next.get(mid, 0.0):
                    self.stream_next[mid] = self.stream_next.get(mid, ts) + interval
                    if self.stream_next[mid] < ts:
                        self.stream_next[mid] = ts + interval
                    msg = self._imu_message(mid, ts, temp)
                    if msg is not None:
                        out.append(msg)
        del mav
        return out

    def _imu_message(self, mid: int, ts: float, temp: float) -> Any:
        d = self.d
        gyro_dps = self.raw_offset_dps(np.array([temp]))[0] + self._rng.normal(0.0, self.noise_dps, 3)
        gyro_dps = self.to_body(gyro_dps - self.compensation_dps(temp))  # sensor -> body, after the offsets
        acc = np.array([0.0, 0.0, -G0]) + self._rng.normal(0.0, 0.02, 3)  # level, at rest, FRD
        usec = int(round(ts * 1e6))
        if mid == 105 and self.kind == "px4":
            g = gyro_dps * RAD
            return d.MAVLink_highres_imu_message(
                usec, *acc, *g, 0.2, 0.0, 0.4, 1013.0, 0.0, 100.0, temp - 3.0, 0x1FFF, 0
            )  # baro temperature, not the IMU's
        temp_c = 0 if self.faults.no_temperature else int(max(-32768, min(32767, temp * 100.0)))
        mrad = [int(v) for v in gyro_dps * RAD * 1000.0]  # C float -> int16 truncates toward zero
        mg = [int(v) for v in acc * 1000.0 / G0]
        if mid == 27 and self.kind == "ardupilot":
            return d.MAVLink_raw_imu_message(usec, *mg, *mrad, 0, 0, 0, 0, temp_c)
        if mid == 26:
            return d.MAVLink_scaled_imu_message(int(ts * 1000), *mg, *mrad, 0, 0, 0,
                                                (temp_c or 1) if not self.faults.no_temperature else 0)
        return None

    # -- host messages --------------------------------------------------------------------------
    def handle(self, msg: Any, t_s: float) -> list[Any]:
        kind = msg.get_type()
        if kind in ("PARAM_SET", "PARAM_REQUEST_READ", "COMMAND_LONG") and getattr(
            msg, "target_system", self.sysid
        ) not in (0, self.sysid):
            return []
        muted = t_s < self._params_muted_until
        if kind == "PARAM_REQUEST_READ":
            name = _name(msg.param_id)
            return [self._param_value(name)] if name in self.params and not muted else []
        if kind == "PARAM_SET":
            out = self._param_set(msg, t_s)
            f = self.faults
            if f.mute_params_after_sets and self.sets_seen == f.mute_params_after_sets:
                f.mute_params_after_sets = 0
                self._params_muted_until = t_s + f.silence_s
            return [] if t_s < self._params_muted_until else out
        if kind == "COMMAND_LONG":
            return self._command(msg, t_s)
        return []

    def _param_value(self, name: str) -> Any:
        ptype = self.ptypes[name]
        wire = encode_param(self.params[name], ptype, self.profile.bytewise)
        return self.d.MAVLink_param_value_message(
            name.encode("ascii"), wire, ptype, len(self.order), self.order.index(name)
        )

    def _param_set(self, msg: Any, t_s: float) -> list[Any]:
        name = _name(msg.param_id)
        if name not in self.params:
            return []  # both autopilots ignore an unknown name (no PARAM_VALUE)
        ptype = self.ptypes[name]
        value = decode_param(float(msg.param_value), ptype, self.profile.bytewise)
        if name == self.faults.reject_param:
            value = self.params[name]  # refused: the echo carries the value it keeps
        self.params[name] = f32(value) if ptype == REAL32 else float(int(value))
        if self.kind == "px4" and self.boot.tc_running:
            self._px4_poll(t_s, self.temp_c(t_s), force=True)  # parameter_update -> reload
        self.sets_seen += 1
        if self.faults.reboot_after_sets and self.sets_seen == self.faults.reboot_after_sets:
            self.faults.reboot_after_sets = 0
            self.reboot_pending = True
            return []
        if self.faults.silence_after_sets and self.sets_seen == self.faults.silence_after_sets:
            self.faults.silence_after_sets = 0
            self.silence_pending = True
            return []
        if self.faults.drop_param_values > 0:
            self.faults.drop_param_values -= 1
            return []
        return [self._param_value(name)]

    def _command(self, msg: Any, t_s: float) -> list[Any]:
        d = self.d
        cmd, result = int(msg.command), 0
        out: list[Any] = []
        if cmd == 511:  # SET_MESSAGE_INTERVAL: param1 message id, param2 interval [us] (-1 off, 0 default)
            mid, interval = int(msg.param1), float(msg.param2)
            supported = {105, 26} if self.kind == "px4" else {27}
            if mid not in supported:
                result = 4  # MAV_RESULT_FAILED: this firmware does not stream it
            elif interval < 0:
                self.streams.pop(mid, None)
            else:
                self.streams[mid] = max(interval * 1e-6 if interval > 0 else 0.1, 1.0 / self.rate_hz)
                self.stream_next[mid] = t_s
        elif cmd == 512:  # REQUEST_MESSAGE
            if int(msg.param1) == 148:
                out.append(self._version())
            else:
                result = 4
        elif cmd == 520:  # legacy REQUEST_AUTOPILOT_CAPABILITIES
            out.append(self._version())
        elif cmd == 246:  # PREFLIGHT_REBOOT_SHUTDOWN: param1 = 1 reboots the autopilot
            if int(msg.param1) == 1:
                self.reboot_pending = True
            else:
                result = 3
        else:
            result = 3  # MAV_RESULT_UNSUPPORTED
        return [d.MAVLink_command_ack_message(cmd, result), *out]

    def _version(self) -> Any:
        d = self.d
        if self.kind == "px4":
            caps, fw = 16 | 8192, (1 << 24) | (14 << 16) | (0 << 8) | 255
        else:
            caps, fw = 131072 | 8192, (4 << 24) | (5 << 16) | (7 << 8) | 255
        uid2 = list(struct.pack("<Q", self.uid)) + [0] * 10
        return d.MAVLink_autopilot_version_message(
            caps, fw, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0x26AC, 0x11, self.uid, uid2
        )

    def status(self) -> dict[str, Any]:
        t = self.boot.sample_index / self.rate_hz
        temp = self.temp_c(t)
        return {
            "autopilot": self.kind,
            "boot": self.boot_count,
            "t_s": t,
            "temp_c": temp,
            "offset_error_dps": self.offset_error_dps(temp).tolist(),
            "params": {k: v for k, v in self.params.items()},
        }


def _name(raw: Any) -> str:
    text = raw if isinstance(raw, str) else bytes(raw).decode("ascii", "replace")
    return text.rstrip("\x00")


__all__ = ["AutopilotFaults", "VirtualAutopilot", "default_thermal_dps", "INT32", "INT8", "REAL32"]
