"""The unit's side of the wire protocol, written from docs/protocol.md only.

Nothing here imports gyrocal: a unit vendor gets the document and the DBC, not the host's code.
All integers little-endian; floats float64 little-endian; gyro 1e-6 deg/s, accel 1e-4 g (serial),
temperature 0.01 degC, time in microseconds since switch-on.
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass, field

import numpy as np

SYNC = b"\xa5\x5a"
MAX_PAYLOAD = 512

HELLO, SAMPLE, HELLO_REQUEST = 0x01, 0x02, 0x03
COEFF_WRITE, COEFF_ACK, COEFF_NAK, COEFF_READ, COEFF_REPORT = 0x10, 0x11, 0x12, 0x13, 0x14

NAK_BAD_CRC, NAK_UNKNOWN_TERMS, NAK_OUT_OF_RANGE, NAK_BUSY, NAK_INCOMPLETE, NAK_BAD_LENGTH = 1, 2, 3, 4, 5, 6

MAX_TERMS = 21


def _set_length_ok(length: int) -> bool:
    return length >= 7 and (length - 7) % 24 == 0 and (length - 7) // 24 <= MAX_TERMS


# Which payload lengths each type may have (receiver rule 2: reject on the header alone).
LENGTH_OK = {
    HELLO: lambda n: n == 13,
    SAMPLE: lambda n: n == 32,
    HELLO_REQUEST: lambda n: n == 0,
    COEFF_WRITE: _set_length_ok,
    COEFF_ACK: lambda n: n == 8,
    COEFF_NAK: lambda n: n == 9,
    COEFF_READ: lambda n: n == 0,
    COEFF_REPORT: _set_length_ok,
}


def crc32(data: bytes) -> int:
    """CRC-32/ISO-HDLC (check "123456789" = 0xCBF43926)."""
    return binascii.crc32(data) & 0xFFFFFFFF


def terms_id(names: list[str]) -> int:
    """CRC-16/CCITT-FALSE over the names, spaces removed, joined by ','."""
    text = ",".join(n.replace(" ", "") for n in names)
    return binascii.crc_hqx(text.encode("ascii"), 0xFFFF)


SEED000 = ["1", "gx", "gy", "gz", "gx^2", "gy^2", "gz^2", "gx*gy", "gy*gz", "gx*gz"]
SEED000_TEMP = [*SEED000, "temp", "temp^2", "dtemp", "temp*dtemp"]
# The unit's table of the term sets it can evaluate: terms_id -> names.
TERM_TABLE: dict[int, list[str]] = {terms_id(SEED000): SEED000, terms_id(SEED000_TEMP): SEED000_TEMP}


def frame(ftype: int, payload: bytes) -> bytes:
    """One serial frame: sync, type, length, payload, CRC over type..payload (LE)."""
    body = struct.pack("<BH", ftype, len(payload)) + payload
    return SYNC + body + struct.pack("<I", crc32(body))


def sat(value: float, lsb: float, bits: int) -> int:
    """Round to the nearest count and saturate to a signed field (firmware saturates, doc sec. 1)."""
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return int(min(hi, max(lo, round(value / lsb))))


def sample_payload(seq: int, t_us: int, gyro: np.ndarray, accel: np.ndarray, temp: float) -> bytes:
    return struct.pack(
        "<IQiiihhhh", seq & 0xFFFFFFFF, t_us,
        *(sat(float(g), 1e-6, 32) for g in gyro), *(sat(float(a), 1e-4, 16) for a in accel),
        sat(temp, 0.01, 16))


def hello_payload(serial: int, fw: tuple[int, int, int], boot: int, rate_hz: int) -> bytes:
    return struct.pack("<IBBBIH", serial, *fw, boot, rate_hz)


@dataclass(frozen=True)
class CoeffSet:
    """A coefficient set: version, terms_id and a 3 x n matrix [deg/s per unit of term]."""

    version: int
    terms_id: int
    coeffs: np.ndarray = field(compare=False)

    @property
    def n(self) -> int:
        return int(self.coeffs.shape[1])

    def encode(self) -> bytes:
        """Canonical encoding: version u32, terms_id u16, n u8, then x, y, z rows of float64."""
        flat = self.coeffs.reshape(-1)
        return struct.pack("<IHB", self.version, self.terms_id, self.n) + struct.pack(f"<{flat.size}d", *flat)

    @property
    def crc(self) -> int:
        return crc32(self.encode())

    @staticmethod
    def empty() -> CoeffSet:
        return CoeffSet(0, 0, np.zeros((3, 0)))

    @staticmethod
    def decode(data: bytes) -> CoeffSet:
        """Raise ValueError when n disagrees with the length (a serial frame is then dropped)."""
        if len(data) < 7:
            raise ValueError("set shorter than its header")
        version, tid, n = struct.unpack_from("<IHB", data)
        if len(data) != 7 + 24 * n:
            raise ValueError(f"n={n} disagrees with length {len(data)}")
        vals = struct.unpack_from(f"<{3 * n}d", data, 7)
        return CoeffSet(version, tid, np.array(vals, dtype=float).reshape(3, n))


def evaluate_terms(names: list[str], accel: np.ndarray, temp: np.ndarray, dtemp: np.ndarray,
                   t_s: np.ndarray) -> np.ndarray:
    """Terms (N x n) per sample from that sample's own measurements (doc sec. 6).

    Gravity terms use the unit vector a/|a| of the measured specific force [g]; |a| = 0 gives 0.
    temp [degC], dtemp [degC/s], t_on [s].
    """
    norm = np.linalg.norm(accel, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.where(norm > 0, accel / np.where(norm > 0, norm, 1.0), 0.0)
    env = {"gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2], "temp": temp, "dtemp": dtemp, "t_on": t_s}
    cols = []
    for name in names:
        val = np.ones(len(accel))
        for factor in name.split("*"):
            base, _, power = factor.partition("^")
            if base == "1":
                continue
            val = val * env[base] ** (int(power) if power else 1)
        cols.append(val)
    return np.column_stack(cols) if cols else np.zeros((len(accel), 0))


class TempRateRule:
    """dtemp [degC/s] per doc sec. 6: LS slope of the last 20 whole-second temperature means.

    At the end of each whole second of unit time the mean of that second's temperatures (as sent)
    is taken against the mid-second time floor(t) + 0.5; dtemp is 0 until three means exist.
    """

    def __init__(self, lag_s: int = 0) -> None:
        self.lag_s = lag_s  # diagnostic only: use the slope of lag_s whole seconds earlier
        self.history: list[float] = [0.0]
        self.second: int | None = None
        self.acc = 0.0
        self.count = 0
        self.means: list[tuple[float, float]] = []
        self.value = 0.0

    def step(self, t_s: float, temp: float) -> float:
        """Feed one sample; return the dtemp in force when it was taken."""
        sec = math.floor(t_s)
        if self.second is not None and sec != self.second and self.count:
            self.means.append((self.second + 0.5, self.acc / self.count))
            self.means = self.means[-20:]
            if len(self.means) >= 3:
                x = np.array([m[0] for m in self.means])
                y = np.array([m[1] for m in self.means])
                xc = x - x.mean()
                self.value = float(np.dot(xc, y - y.mean()) / np.dot(xc, xc))
            self.history = [*self.history[-(self.lag_s + 1):], self.value]
            self.acc, self.count = 0.0, 0
        self.second = sec
        used = self.history[-1 - self.lag_s] if len(self.history) > self.lag_s else 0.0
        self.acc += temp
        self.count += 1
        return used


@dataclass
class RxStats:
    """Receiver counters (doc sec. 5 names)."""

    frames: int = 0
    bytes: int = 0
    crc_errors: int = 0
    resyncs: int = 0
    oversize: int = 0
    length_errors: int = 0
    garbage_bytes: int = 0
    unknown_types: int = 0
    incomplete: int = 0
    foreign_frames: int = 0


class SerialReceiver:
    """Receiver rules 1-5: hunt sync, reject on the header, wait, CRC, drop one byte on rejection."""

    def __init__(self) -> None:
        self.buf = bytearray()
        self.stats = RxStats()

    def _reject(self, counter: str) -> None:
        setattr(self.stats, counter, getattr(self.stats, counter) + 1)
        self.stats.resyncs += 1
        del self.buf[:1]

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        self.stats.bytes += len(data)
        self.buf += data
        out: list[tuple[int, bytes]] = []
        while True:
            idx = self.buf.find(SYNC)
            if idx < 0:
                keep = 1 if self.buf.endswith(SYNC[:1]) else 0
                self.stats.garbage_bytes += len(self.buf) - keep
                del self.buf[: len(self.buf) - keep]
                return out
            if idx:
                self.stats.garbage_bytes += idx
                del self.buf[:idx]
            if len(self.buf) < 5:
                return out
            ftype, length = struct.unpack_from("<BH", self.buf, 2)
            if ftype not in LENGTH_OK:
                self._reject("unknown_types")
                continue
            if length > MAX_PAYLOAD:
                self._reject("oversize")
                continue
            if not LENGTH_OK[ftype](length):
                self._reject("length_errors")
                continue
            if len(self.buf) < 9 + length:
                return out
            body = bytes(self.buf[2:5 + length])
            (sent,) = struct.unpack_from("<I", self.buf, 5 + length)
            if crc32(body) != sent:
                self._reject("crc_errors")
                continue
            del self.buf[: 9 + length]
            self.stats.frames += 1
            out.append((ftype, body[3:]))
