"""Serial framing: messages <-> a byte stream with sync word, type, length, payload and CRC-32.

A frame is (all little-endian, docs/protocol.md gives each payload byte by byte)::

    A5 5A | type u8 | length u16 | payload (length bytes, <= 512) | crc32 u32 over type..payload

The decoder faces what gpsd's packet.c faces: garbage before and between frames (a unit that boots
mid-frame, line noise, a reader that starts in the middle of a stream). Its policy is gpsd's: hunt
for the sync word; cap the length; on any bad candidate (an unknown type, a length above the cap
or one the type cannot have, a CRC failure) count it and drop ONE byte, then rescan. A valid frame
hidden behind a false sync is therefore found again, so the decoder is back in step within one
frame length, and no frame whose CRC fails is ever yielded. The decoder is pure: bytes in, messages
out, no I/O, no threads, and it never holds more than one maximal frame (521 bytes) between calls.
"""

from __future__ import annotations

import binascii
import math
import struct
from collections.abc import Callable

from gyrocal.errors import ProtocolError
from gyrocal.protocol.messages import (
    ACCEL_PER_G_SERIAL,
    GYRO_PER_DPS,
    MAX_TERMS,
    TEMP_PER_C,
    US_PER_S,
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffWrite,
    Hello,
    HelloRequest,
    NakReason,
    Sample,
    SampleConflict,
    check_int,
    coeff_set_bytes,
    parse_coeff_set,
    parse_fw_version,
    quantise,
)
from gyrocal.protocol.stats import DecoderStats

SYNC = b"\xa5\x5a"
"""Sync word: alternating bits, and 0xA5 is rare in small little-endian integers."""
MAX_PAYLOAD = 512
"""Length cap [bytes]; a larger length field is counted as oversize and resynced."""
HEADER_SIZE = 5
CRC_SIZE = 4
MAX_FRAME = HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE

T_HELLO = 0x01
T_HELLO_REQUEST = 0x03
T_SAMPLE = 0x02
T_COEFF_WRITE = 0x10
T_COEFF_ACK = 0x11
T_COEFF_NAK = 0x12
T_COEFF_READ = 0x13
T_COEFF_REPORT = 0x14

_HEADER = struct.Struct("<2sBH")
_TYPE_LEN = struct.Struct("<BH")
_CRC = struct.Struct("<I")
SAMPLE_PAYLOAD = struct.Struct("<IQiiihhhh")
"""seq u32, t_us u64, gyro xyz i32 [1e-6 deg/s], accel xyz i16 [1e-4 g], temp i16 [0.01 degC]: 32 bytes."""
HELLO_PAYLOAD = struct.Struct("<IBBBIH")
"""serial u32, fw major/minor/patch u8, boot_count u32, rate_hz u16: 13 bytes."""
ACK_PAYLOAD = struct.Struct("<II")
NAK_PAYLOAD = struct.Struct("<IIB")

SAMPLE_FRAME_SIZE = HEADER_SIZE + SAMPLE_PAYLOAD.size + CRC_SIZE
"""41 bytes on the wire per sample."""

_I32 = 0x7FFFFFFF
_I16 = 0x7FFF


def _coeff_len_ok(n: int) -> bool:
    return n >= 7 and (n - 7) % 24 == 0 and (n - 7) // 24 <= MAX_TERMS


_LENGTH_OK: dict[int, Callable[[int], bool]] = {
    T_SAMPLE: lambda n: n == SAMPLE_PAYLOAD.size,
    T_HELLO: lambda n: n == HELLO_PAYLOAD.size,
    T_COEFF_ACK: lambda n: n == ACK_PAYLOAD.size,
    T_COEFF_NAK: lambda n: n == NAK_PAYLOAD.size,
    T_COEFF_READ: lambda n: n == 0,
    T_HELLO_REQUEST: lambda n: n == 0,
    T_COEFF_WRITE: _coeff_len_ok,
    T_COEFF_REPORT: _coeff_len_ok,
}


def _sample_payload(m: Sample) -> bytes:
    g, a = m.gyro_dps, m.accel_g
    try:
        return SAMPLE_PAYLOAD.pack(
            m.seq, round(m.t_s * US_PER_S),
            round(g[0] * GYRO_PER_DPS), round(g[1] * GYRO_PER_DPS), round(g[2] * GYRO_PER_DPS),
            round(a[0] * ACCEL_PER_G_SERIAL), round(a[1] * ACCEL_PER_G_SERIAL),
            round(a[2] * ACCEL_PER_G_SERIAL), round(m.temp_c * TEMP_PER_C),
        )
    except (struct.error, ValueError, OverflowError, TypeError, IndexError):
        pass  # the fast path failed: find the field to name it
    check_int("seq", m.seq, 0, 0xFFFFFFFF)
    quantise("t_s", m.t_s, US_PER_S, 0, 2**64 - 1)
    for k, name in enumerate("xyz"):
        quantise(f"gyro_dps.{name}", g[k], GYRO_PER_DPS, -_I32 - 1, _I32)
        quantise(f"accel_g.{name}", a[k], ACCEL_PER_G_SERIAL, -_I16 - 1, _I16)
    quantise("temp_c", m.temp_c, TEMP_PER_C, -_I16 - 1, _I16)
    raise ProtocolError(f"sample {m!r} cannot be encoded")


def encode_payload(msg: object) -> tuple[int, bytes]:
    """(frame type, payload bytes) of a message; ProtocolError if a field is out of its range."""
    if isinstance(msg, Sample):
        return T_SAMPLE, _sample_payload(msg)
    if isinstance(msg, Hello):
        major, minor, patch = parse_fw_version(msg.fw_version)
        serial = check_int("serial", msg.serial, 0, 0xFFFFFFFF)
        boots = check_int("boot_count", msg.boot_count, 0, 0xFFFFFFFF)
        rate = check_int("rate_hz", msg.rate_hz, 0, 0xFFFF)
        return T_HELLO, HELLO_PAYLOAD.pack(serial, major, minor, patch, boots, rate)
    if isinstance(msg, CoeffWrite | CoeffReport):
        typ = T_COEFF_WRITE if isinstance(msg, CoeffWrite) else T_COEFF_REPORT
        return typ, coeff_set_bytes(msg.version, msg.terms_id, msg.coeffs_dps)
    if isinstance(msg, CoeffAck):
        version = check_int("version", msg.version, 0, 0xFFFFFFFF)
        crc = check_int("crc", msg.crc, 0, 0xFFFFFFFF)
        return T_COEFF_ACK, ACK_PAYLOAD.pack(version, crc)
    if isinstance(msg, CoeffNak):
        version = check_int("version", msg.version, 0, 0xFFFFFFFF)
        crc = check_int("crc", msg.crc, 0, 0xFFFFFFFF)
        reason = check_int("reason", msg.reason, 0, 255)
        return T_COEFF_NAK, NAK_PAYLOAD.pack(version, crc, reason)
    if isinstance(msg, CoeffRead):
        return T_COEFF_READ, b""
    if isinstance(msg, HelloRequest):
        return T_HELLO_REQUEST, b""
    raise ProtocolError(f"{type(msg).__name__} has no serial frame type")


def encode_frame(msg: object) -> bytes:
    """One complete serial frame (sync, header, payload, CRC) for a message."""
    typ, payload = encode_payload(msg)
    head = _TYPE_LEN.pack(typ, len(payload))
    return SYNC + head + payload + _CRC.pack(binascii.crc32(payload, binascii.crc32(head)))


def _nak_reason(code: int) -> int:
    try:
        return NakReason(code)
    except ValueError:
        return code


MAX_COUNTED_GAP = 1 << 20
"""A forward seq jump up to this many samples counts as lost samples; a farther one is an outlier or a
restart (the engine tells which), not 17 minutes of 1 kHz samples lost."""


class NonFiniteCoefficients(ProtocolError):
    """A coefficient set frame whose values are not all finite (counted as ``bad_values``)."""


def decode_payload(typ: int, payload: bytes | memoryview) -> object:
    """Message of a checked frame; ProtocolError if the payload does not fit the type's layout."""
    if typ == T_SAMPLE:
        seq, t_us, gx, gy, gz, ax, ay, az, tc = SAMPLE_PAYLOAD.unpack(payload)
        return Sample(seq, t_us / US_PER_S, (gx / GYRO_PER_DPS, gy / GYRO_PER_DPS, gz / GYRO_PER_DPS),
                      (ax / ACCEL_PER_G_SERIAL, ay / ACCEL_PER_G_SERIAL, az / ACCEL_PER_G_SERIAL),
                      tc / TEMP_PER_C)
    try:
        if typ == T_HELLO:
            serial, major, minor, patch, boots, rate = HELLO_PAYLOAD.unpack(payload)
            return Hello(serial, f"{major}.{minor}.{patch}", boots, rate)
        if typ in (T_COEFF_WRITE, T_COEFF_REPORT):
            version, tid, rows = parse_coeff_set(payload)
            if not all(math.isfinite(c) for row in rows for c in row):
                # a CRC-valid frame can still carry NaN/Inf (a unit's bug, a fuzzer): no such set
                # exists on the wire (coeff_set_bytes refuses to encode it), so drop and count it,
                # as the CAN decoder does; the host reads again after its timeout
                raise NonFiniteCoefficients(
                    f"frame type 0x{typ:02X}: coefficient set v{version} holds NaN or Inf")
            return (CoeffWrite if typ == T_COEFF_WRITE else CoeffReport)(version, tid, rows)
        if typ == T_COEFF_ACK:
            return CoeffAck(*ACK_PAYLOAD.unpack(payload))
        if typ == T_COEFF_NAK:
            version, crc, reason = NAK_PAYLOAD.unpack(payload)
            return CoeffNak(version, crc, _nak_reason(reason))
        if typ == T_COEFF_READ and len(payload) == 0:
            return CoeffRead()
        if typ == T_HELLO_REQUEST and len(payload) == 0:
            return HelloRequest()
    except struct.error as err:
        raise ProtocolError(f"frame type 0x{typ:02X}: payload of {len(payload)} bytes: {err}") from err
    raise ProtocolError(f"frame type 0x{typ:02X} with {len(payload)} payload bytes is not known")


class FrameDecoder:
    """Streaming decoder: ``feed(bytes) -> list of messages``; counters in ``.stats``.

    It yields only frames whose CRC-32 matches. SAMPLE seq continuity is checked (u32 wrap allowed)
    and reset by HELLO, since the unit restarts seq at every switch-on.
    """

    def __init__(self, max_payload: int = MAX_PAYLOAD) -> None:
        self.max_payload = min(int(max_payload), MAX_PAYLOAD)
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._last_seq: int | None = None
        self._last_sample: object = None  # the last sample yielded, to tell a copy from a conflict
        self.mark_conflicts = False  # a log reader's: yield SampleConflict for a conflicting copy
        self._locked = False

    def reset(self) -> None:
        """Forget buffered bytes and seq state (e.g. after the port reopened); keep the counters."""
        self._buf.clear()
        self._last_seq = None
        self._locked = False

    @property
    def buffered(self) -> int:
        """Bytes held for an unfinished frame (at most one maximal frame)."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[object]:
        """Add received bytes; return the messages completed by them, in stream order."""
        st = self.stats
        st.bytes += len(data)
        buf = self._buf
        buf += data
        out: list[object] = []
        n = len(buf)
        pos = 0
        cap = self.max_payload
        length_ok = _LENGTH_OK
        crc32 = binascii.crc32
        mv = memoryview(buf)
        try:
            while True:
                i = buf.find(SYNC, pos)
                if i < 0:
                    keep = n - 1 if n > pos and buf[n - 1] == SYNC[0] else n
                    self._garbage(keep - pos)
                    pos = keep
                    break
                if i > pos:
                    self._garbage(i - pos)
                    pos = i
                if n - pos < HEADER_SIZE:
                    break
                typ, length = _TYPE_LEN.unpack_from(buf, pos + 2)
                check = length_ok.get(typ)
                if check is None or length > cap or not check(length):
                    # Judged on the header alone, so a false sync never stalls the stream waiting
                    # for up to 512 bytes of a frame that cannot be valid.
                    if check is None:
                        st.unknown_types += 1
                    elif length > cap:
                        st.oversize += 1
                    else:
                        st.length_errors += 1
                    pos = self._reject(pos)
                    continue
                end = pos + HEADER_SIZE + length + CRC_SIZE
                if end > n:
                    break
                if crc32(mv[pos + 2 : end - CRC_SIZE]) != _CRC.unpack_from(buf, end - CRC_SIZE)[0]:
                    st.crc_errors += 1
                    pos = self._reject(pos)
                    continue
                self._locked = True
                try:
                    msg = decode_payload(typ, mv[pos + HEADER_SIZE : end - CRC_SIZE])
                except NonFiniteCoefficients:
                    st.bad_values += 1
                    pos = end
                    continue
                except ProtocolError:
                    st.length_errors += 1
                    pos = end
                    continue
                pos = end
                if typ == T_SAMPLE:
                    last = self._last_seq
                    seq = msg.seq  # type: ignore[attr-defined]
                    if seq == last:  # the previous sample again: a copy is not a second sample, and
                        if msg == self._last_sample:  # one with other values is another sender
                            st.repeated += 1
                        else:
                            st.conflicting += 1
                            if self.mark_conflicts:
                                out.append(SampleConflict(seq))
                        continue
                    self._last_sample = msg
                    if last is not None and seq != (last + 1) & 0xFFFFFFFF:
                        st.seq_gaps += 1
                        missing = (seq - last - 1) & 0xFFFFFFFF
                        if missing < MAX_COUNTED_GAP:  # else a repeat, a step back or an outlier's far seq
                            st.lost_samples += missing
                    self._last_seq = seq
                elif typ == T_HELLO:
                    self._last_seq = None
                st.frames += 1
                out.append(msg)
        finally:
            mv.release()
        del buf[:pos]
        return out

    def _garbage(self, count: int) -> None:
        if count > 0:
            self.stats.garbage_bytes += count
            if self._locked:
                self.stats.resyncs += 1
                self._locked = False

    def _reject(self, pos: int) -> int:
        """Give up the candidate at pos: count a resync and drop its first byte (gpsd policy)."""
        self.stats.resyncs += 1
        self.stats.garbage_bytes += 1
        self._locked = False
        return pos + 1
