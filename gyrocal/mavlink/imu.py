"""IMU messages -> ``Sample`` in the daemon's units, and switch-on detection.

Which message carries what (docs/mavlink.md cites the senders):

- HIGHRES_IMU (PX4, MavlinkStreamHighresIMU): time_usec = vehicle_imu timestamp_sample [us since
  boot]; x/y/zgyro [rad/s] body frame after CAL_GYRO offsets and TC_G thermal offsets, minus the
  EKF2 gyro bias estimate; x/y/zacc [m/s^2]; ``temperature`` is the barometer's, so it is NOT used.
- RAW_IMU (ArduPilot, send_raw_imu): time_usec [us since boot]; gyro [mrad/s] = ins.get_gyro(0)*1000
  (INS_TCAL and INS_GYROFFS applied, body frame), truncated to int16 (read back at each step's
  centre, see ``bin_centre``); accel [mG]; temperature [cdegC] of IMU 0 (0 = not given).
- SCALED_IMU/2/3 (PX4: vehicle_imu instance 0/1/2; ArduPilot: IMU 1/2): time_boot_ms; gyro [mrad/s];
  accel [mG]; temperature [cdegC] of that IMU (0 = not given).

Axes stay in the autopilot's body frame (FRD): a level vehicle at rest reads az = -1 g.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass

from gyrocal.mavlink.poly import DEG_PER_RAD
from gyrocal.protocol.messages import Sample

G0 = 9.80665
"""Standard gravity [m/s^2] (GRAVITY_MSS in ArduPilot, CONSTANTS_ONE_G in PX4)."""

SCALED_BY_INSTANCE = ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")


def temp_message(autopilot: str, instance: int) -> str:
    """The message that carries the IMU temperature (and the fallback gyro stream) for ``instance``."""
    if autopilot == "ardupilot" and instance == 0:
        return "RAW_IMU"  # ArduPilot sends IMU 0 as RAW_IMU, IMU 1 and 2 as SCALED_IMU2/3
    return SCALED_BY_INSTANCE[instance]


@dataclass
class ImuReading:
    """One decoded IMU message: time since boot [s], gyro [deg/s], accel [g], temp [degC] or None."""

    t_s: float
    gyro_dps: tuple[float, float, float]
    accel_g: tuple[float, float, float]
    temp_c: float | None


def decode(msg: object) -> ImuReading | None:
    """HIGHRES_IMU, RAW_IMU or SCALED_IMU* -> ImuReading; other messages -> None."""
    kind = msg.get_type()  # type: ignore[attr-defined]
    m = msg
    if kind == "HIGHRES_IMU":
        return ImuReading(
            m.time_usec * 1e-6,
            (m.xgyro * DEG_PER_RAD, m.ygyro * DEG_PER_RAD, m.zgyro * DEG_PER_RAD),
            (m.xacc / G0, m.yacc / G0, m.zacc / G0),
            None,
        )
    if kind == "RAW_IMU" or kind in SCALED_BY_INSTANCE:
        t = m.time_usec * 1e-6 if kind == "RAW_IMU" else m.time_boot_ms * 1e-3
        k = 1e-3 * DEG_PER_RAD
        temp = getattr(m, "temperature", 0)
        return ImuReading(
            t,
            (bin_centre(m.xgyro) * k, bin_centre(m.ygyro) * k, bin_centre(m.zgyro) * k),
            (bin_centre(m.xacc) * 1e-3, bin_centre(m.yacc) * 1e-3, bin_centre(m.zacc) * 1e-3),
            temp * 0.01 if temp else None,
        )
    return None


def bin_centre(v: int) -> float:
    """The centre of the interval a C float -> int16 conversion (truncation toward zero) maps to v.

    Truncation puts [v, v+1) on v > 0 and (v-1, v] on v < 0, so a mean of truncated values is biased
    toward zero by up to half a step (0.5 mrad/s = 103 deg/h for the gyro). Taking each bin's centre
    removes most of that bias when the noise dithers the signal over a step or more; the zero bin
    (-1, 1) keeps a smaller bias (docs/mavlink.md).
    """
    return v + 0.5 if v > 0 else (v - 0.5 if v < 0 else 0.0)


def to_sample(seq: int, r: ImuReading, temp_c: float) -> Sample:
    return Sample(seq & 0xFFFFFFFF, r.t_s, r.gyro_dps, r.accel_g, temp_c)


def derive_serial(uid: int, uid2: bytes | list[int] | None, instance: int, sysid: int = 0) -> int:
    """A 32-bit serial for (board, IMU instance): CRC-32 of uid (u64 LE) + uid2 (18 bytes) + instance.

    AUTOPILOT_VERSION.uid is the board's 64-bit unique id and uid2 its 18-byte form (PX4 fills uid2
    from the MCU's UUID). A board that reports neither (all zero) falls back to its system id, which
    is unique only within one vehicle network; the link logs a warning then.
    """
    u2 = bytes(uid2 or b"")
    if uid == 0 and not any(u2):
        data = b"sysid" + bytes([sysid & 0xFF])
    else:
        data = struct.pack("<Q", uid & 0xFFFFFFFFFFFFFFFF) + u2
    return binascii.crc32(data + bytes([instance & 0xFF]))


def fw_text(flight_sw_version: int) -> str:
    """AUTOPILOT_VERSION.flight_sw_version (major<<24|minor<<16|patch<<8|type) -> 'major.minor.patch'."""
    v = int(flight_sw_version)
    return f"{(v >> 24) & 0xFF}.{(v >> 16) & 0xFF}.{(v >> 8) & 0xFF}"


class BootDetector:
    """A new boot: the boot-relative time goes back, or the heartbeat returns after ``silence_s``.

    A returning heartbeat alone may be a cable glitch, so it only raises a suspicion that the next
    time stamp settles (back in time: new boot; forward: the same boot). With no time stamp for
    ``silence_s`` after it, the suspicion stands and counts as a boot.
    """

    def __init__(self, silence_s: float = 3.0, back_margin_s: float = 0.5) -> None:
        self.silence_s, self.back_margin_s = silence_s, back_margin_s
        self.last_t: float | None = None
        self.last_hb: float | None = None
        self._suspect_since: float | None = None

    def on_heartbeat(self, now: float) -> bool:
        gap = self.last_hb is not None and now - self.last_hb > self.silence_s
        self.last_hb = now
        if gap:
            self._suspect_since = now
        if self._suspect_since is not None and now - self._suspect_since > self.silence_s:
            self._suspect_since = None
            self.last_t = None
            return True
        return False

    def on_time(self, t_s: float) -> bool:
        back = self.last_t is not None and t_s < self.last_t - self.back_margin_s
        if self._suspect_since is not None and self.last_t is not None and not back:
            self._suspect_since = None  # the same boot: time went on
        self.last_t = t_s if not back else t_s
        if back:
            self._suspect_since = None
        return back
