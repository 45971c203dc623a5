"""The messages exchanged with the strapdown unit, independent of the link that carries them.

Each message is a frozen dataclass in physical units (deg/s, g, degC, s). The serial framing
(:mod:`gyrocal.protocol.serial_framing`) and the CAN codec (:mod:`gyrocal.protocol.can_codec`) turn
them into bytes; docs/protocol.md gives every field byte by byte.

The fixed-point scalings live here so both links quantise the same way:

- gyro: int32, LSB 1e-6 deg/s (range +-2147.48 deg/s). Drifts are ~1e-3 deg/s, so the quantum must
  be three decades finer than the signal the calibrator estimates.
- accel: int16, LSB 1e-4 g on serial (+-3.2767 g); int12, LSB 1e-3 g on CAN (+-2.047 g).
- temperature: int16, LSB 0.01 degC (+-327.67 degC).
- unit time: microseconds since switch-on.

The coefficient set has one canonical byte encoding (the serial COEFF_WRITE payload); both sides
compute :func:`coeff_set_crc` over it, so an ACK proves the unit applied exactly what was sent.
"""

from __future__ import annotations

import binascii
import math
import operator
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

from gyrocal.errors import ProtocolError

GYRO_LSB_DPS = 1e-6
"""Gyro quantum [deg/s] on both links."""
GYRO_PER_DPS = 1_000_000
ACCEL_PER_G_SERIAL = 10_000
"""Serial accel counts per g (LSB 1e-4 g)."""
ACCEL_PER_G_CAN = 1_000
"""CAN accel counts per g (LSB 1e-3 g, 12-bit field)."""
TEMP_PER_C = 100
"""Temperature counts per degC (LSB 0.01 degC)."""
US_PER_S = 1_000_000
MAX_TERMS = 21
"""Most terms per axis: 7 + 3*21*8 = 511 bytes fits the 512-byte serial payload cap."""


class NakReason(IntEnum):
    """Why the unit refused a coefficient set (COEFF_NAK reason byte)."""

    BAD_CRC = 1
    """The CRC the host sent (CAN commit) does not match the set the unit received."""
    UNKNOWN_TERMS = 2
    """The unit does not know the terms_id."""
    OUT_OF_RANGE = 3
    """A coefficient is NaN, Inf or beyond what the unit can apply."""
    BUSY = 4
    """The unit cannot write its flash now; retry later."""
    INCOMPLETE = 5
    """A CAN transfer was committed with a missing or duplicated chunk."""
    BAD_LENGTH = 6
    """n_terms does not match the term set named by terms_id."""


Vec3 = tuple[float, float, float]
CoeffRows = tuple[tuple[float, ...], ...]
SEQ_MODULO = 1 << 32
"""A sample's seq is a u32: it wraps here."""


@dataclass(frozen=True, slots=True)
class SampleConflict:
    """Not on the wire: a log reader's decoder says that a sample came again with other values
    (another sender on the unit's ids). The copy before it is no more the unit's than this one, so a
    reader drops both (readers/stream.py); the live link never asks for these."""

    seq: int


@dataclass(frozen=True, slots=True)
class Sample:
    """One IMU sample as the unit sends it (compensated output once a set is applied).

    seq: sample counter, u32, +1 per sample, restarts at 0 at switch-on.
    t_s: unit time since switch-on [s] (carried as integer microseconds).
    gyro_dps: angular rate x, y, z [deg/s]; accel_g: specific force x, y, z [g]; temp_c [degC].
    """

    seq: int
    t_s: float
    gyro_dps: Vec3
    accel_g: Vec3
    temp_c: float


@dataclass(frozen=True, slots=True)
class Hello:
    """Sent by the unit at every switch-on; it starts a new calibration session.

    fw_version is "major.minor.patch", each 0..255. rate_hz is the nominal sample rate [Hz], 0 when
    the unit does not say (an extension of docs/INTERFACES.md; it defaults so old callers still work).
    """

    serial: int
    fw_version: str
    boot_count: int
    rate_hz: int = 0


def _rows(coeffs: object) -> CoeffRows:
    """Normalise 3 rows of P coefficients (lists, tuples, numpy) to a tuple of float tuples."""
    try:
        rows = tuple(tuple(float(c) for c in row) for row in coeffs)  # type: ignore[attr-defined]
    except (TypeError, ValueError) as err:
        raise ProtocolError(f"coeffs_dps must be 3 rows of numbers: {err}") from err
    return rows


@dataclass(frozen=True, slots=True)
class CoeffWrite:
    """Host -> unit: apply this coefficient set.

    coeffs_dps: 3 rows (x, y, z axis) of P coefficients [deg/s per term unit], P = len(terms).
    version: calibration version, u32 (u24 on CAN). terms_id: see :mod:`gyrocal.protocol.termsets`.
    """

    version: int
    terms_id: int
    coeffs_dps: CoeffRows

    def __post_init__(self) -> None:
        object.__setattr__(self, "coeffs_dps", _rows(self.coeffs_dps))


@dataclass(frozen=True, slots=True)
class CoeffReport:
    """Unit -> host: the set the unit applies now (answer to COEFF_READ). Same fields as CoeffWrite."""

    version: int
    terms_id: int
    coeffs_dps: CoeffRows

    def __post_init__(self) -> None:
        object.__setattr__(self, "coeffs_dps", _rows(self.coeffs_dps))


@dataclass(frozen=True, slots=True)
class CoeffAck:
    """Unit -> host: the set is applied and stored; crc = coeff_set_crc of the set as applied."""

    version: int
    crc: int


@dataclass(frozen=True, slots=True)
class CoeffNak:
    """Unit -> host: the set was refused; crc is that of the set received (0 if none), reason a NakReason."""

    version: int
    crc: int
    reason: int


@dataclass(frozen=True, slots=True)
class CoeffRead:
    """Host -> unit: report the applied set (the unit answers with CoeffReport)."""


@dataclass(frozen=True, slots=True)
class HelloRequest:
    """Host -> unit: announce yourself (the unit answers with Hello, boot counter unchanged).

    A unit sends HELLO once, at switch-on. A host that starts, restarts or reconnects after that
    moment (a daemon restarted by its watchdog; a pty or CAN listener opened late) would otherwise
    never learn which unit it talks to until the next power cycle.
    """


@dataclass(frozen=True, slots=True)
class CoeffTransferFailed:
    """Local event of the CAN decoder on the unit side, never sent on a wire.

    A COEFF_COMMIT arrived but the transfer was incomplete (missing or duplicated chunk, no BEGIN) or
    its CRC did not match. The unit must answer ``CoeffNak(version, crc, reason)`` and keep its set.
    """

    version: int
    crc: int
    reason: int


Message = Sample | Hello | HelloRequest | CoeffWrite | CoeffReport | CoeffAck | CoeffNak | CoeffRead


def check_int(name: str, value: int, lo: int, hi: int) -> int:
    """Return value as int if it is an integer (numpy ones too) in lo..hi, else raise ProtocolError."""
    try:
        num = operator.index(value)
    except TypeError:
        raise ProtocolError(f"{name}={value!r} must be an integer") from None
    if not lo <= num <= hi:
        raise ProtocolError(f"{name}={value!r} is outside its wire range {lo}..{hi}")
    return num


def quantise(name: str, value: float, per_unit: int, lo: int, hi: int) -> int:
    """Round a physical value to its integer wire count; raise ProtocolError if it does not fit."""
    try:
        raw = int(round(value * per_unit))
    except (TypeError, ValueError, OverflowError) as err:
        raise ProtocolError(f"{name}={value!r} cannot be encoded: {err}") from err
    if not lo <= raw <= hi:
        raise ProtocolError(f"{name}={value!r} is outside its wire range {lo / per_unit}..{hi / per_unit}")
    return raw


def parse_fw_version(text: str) -> tuple[int, int, int]:
    """'1.2.3' -> (1, 2, 3), each part 0..255."""
    parts = str(text).split(".")
    if len(parts) != 3 or not all(p.isdigit() for p in parts):
        raise ProtocolError(f"fw_version={text!r} must be 'major.minor.patch', e.g. '1.2.3'")
    nums = tuple(int(p) for p in parts)
    for n in nums:
        check_int("fw_version part", n, 0, 255)
    return nums  # type: ignore[return-value]


_COEFF_HEAD = struct.Struct("<IHB")


def coeff_set_bytes(version: int, terms_id: int, coeffs_dps: Sequence[Sequence[float]]) -> bytes:
    """The canonical encoding of a set: version u32, terms_id u16, n u8, then x, y, z rows of float64.

    It is the serial COEFF_WRITE / COEFF_REPORT payload and the input of :func:`coeff_set_crc`.
    """
    rows = _rows(coeffs_dps)
    if len(rows) != 3:
        raise ProtocolError(f"coeffs_dps has {len(rows)} rows; it needs 3 (x, y, z)")
    n = len(rows[0])
    if any(len(r) != n for r in rows):
        raise ProtocolError(f"coeffs_dps rows have lengths {[len(r) for r in rows]}; they must be equal")
    check_int("n_terms", n, 0, MAX_TERMS)
    version = check_int("version", version, 0, 0xFFFFFFFF)
    terms_id = check_int("terms_id", terms_id, 0, 0xFFFF)
    flat = [c for r in rows for c in r]
    if not all(math.isfinite(c) for c in flat):
        raise ProtocolError("coeffs_dps holds NaN or Inf; the unit cannot apply it")
    return _COEFF_HEAD.pack(version, terms_id, n) + struct.pack(f"<{3 * n}d", *flat)


def parse_coeff_set(payload: bytes | memoryview) -> tuple[int, int, CoeffRows]:
    """Inverse of :func:`coeff_set_bytes`; raise ProtocolError if the length does not match n."""
    if len(payload) < _COEFF_HEAD.size:
        raise ProtocolError("coefficient payload shorter than its 7-byte header")
    version, terms_id, n = _COEFF_HEAD.unpack_from(payload)
    if n > MAX_TERMS or len(payload) != _COEFF_HEAD.size + 24 * n:
        raise ProtocolError(f"coefficient payload of {len(payload)} bytes does not match n_terms={n}")
    flat = struct.unpack_from(f"<{3 * n}d", payload, _COEFF_HEAD.size)
    return version, terms_id, (flat[:n], flat[n : 2 * n], flat[2 * n :])


def coeff_set_crc(version: int, terms_id: int, coeffs_dps: Sequence[Sequence[float]]) -> int:
    """CRC-32 (IEEE, as zlib.crc32) of :func:`coeff_set_bytes`; the ACK's crc must equal it."""
    return binascii.crc32(coeff_set_bytes(version, terms_id, coeffs_dps))
