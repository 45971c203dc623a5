"""CAN link: messages <-> classic CAN frames (8 data bytes, 11-bit ids) defined in configs/gyrocal.dbc.

The DBC is the single source of the frame layouts; cantools packs and unpacks the raw signal values
and this module does the scaling and range checks itself, so both links quantise identically and an
out-of-range value raises ProtocolError instead of being clipped.

Frame id = 0x100 + (function << 4) + node_id (node_id 0..15); the DBC holds node 0's ids. Lower ids
win arbitration, so the rare control frames (HELLO, ACK, coefficients) beat the sample stream.

A SAMPLE takes three frames, SAMPLE_A/B/C (ascending ids, so a unit that queues all three in
mailboxes still sends them in order): 2000 samples/s x 3 = 6000 frames/s, three quarters of the
~8000 frames/s a 1 Mbit/s bus carries. The 20-bit microsecond time in B and C is unwrapped against
the previous sample; a SAMPLE_TIME anchor with the full 48-bit time precedes the first sample, every
sample with seq % 256 == 0, and any sample 1 s or more after the last anchor.

Coefficient sets are sent as BEGIN, 6*n DATA chunks (each float64 split into two 32-bit words),
COMMIT with coeff_set_crc; the receiver applies nothing unless every chunk arrived exactly once and
the CRC matches (docs/protocol.md, "Multi-frame transfers").
"""

from __future__ import annotations

import functools
import struct
from pathlib import Path

import can
import cantools

from gyrocal.errors import ProtocolError
from gyrocal.protocol.can_reassembly import CanDecoder
from gyrocal.protocol.messages import (
    ACCEL_PER_G_CAN,
    GYRO_PER_DPS,
    TEMP_PER_C,
    US_PER_S,
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffWrite,
    Hello,
    HelloRequest,
    Sample,
    check_int,
    coeff_set_bytes,
    coeff_set_crc,
    parse_fw_version,
    quantise,
)

DEFAULT_DBC = Path(__file__).resolve().parent.parent / "configs" / "gyrocal.dbc"
ID_BASE = 0x100
ANCHOR_EVERY = 256
"""A SAMPLE_TIME anchor goes before every sample with seq % ANCHOR_EVERY == 0."""
ANCHOR_MAX_US = 1_000_000
"""... and before any sample this long [us] after the previous anchor."""
CAN_VERSION_MAX = 0xFFFFFF
"""COEFF_NAK has room for 24 version bits, so calibration versions on CAN stay below 2**24."""
T20_MASK = 0xFFFFF

__all__ = ["ANCHOR_EVERY", "CanCodec", "CanDecoder", "DEFAULT_DBC", "load_dbc"]


@functools.lru_cache(maxsize=4)
def load_dbc(path: str | None = None) -> cantools.database.can.Database:
    """Load (once per path) and return the cantools database; the default is the packaged DBC."""
    return cantools.database.load_file(str(path or DEFAULT_DBC), strict=True)


class CanCodec:
    """Encoder for one node: ``encode(msg) -> list[can.Message]``; ``decoder()`` makes its CanDecoder.

    It keeps one piece of state, the time of the last SAMPLE_TIME anchor it emitted, so use one codec
    per link direction.
    """

    def __init__(self, dbc_path: str | Path | None = None, node_id: int = 0) -> None:
        self.node_id = check_int("node_id", node_id, 0, 15)
        self.db = load_dbc(str(dbc_path) if dbc_path else None)
        self.by_name = {m.name: m for m in self.db.messages}
        for m in self.db.messages:
            if m.frame_id & 0xF or not ID_BASE <= m.frame_id < ID_BASE + 0x100:
                raise ProtocolError(f"{dbc_path or DEFAULT_DBC}: frame {m.name} id 0x{m.frame_id:X} is not "
                                    "0x100 + (function << 4) with node 0")
        self.ids = {m.name: m.frame_id + node_id for m in self.db.messages}
        self._last_anchor_us: int | None = None

    def decoder(self) -> CanDecoder:
        """A fresh decoder for frames of this codec's node."""
        return CanDecoder(self)

    def _frame(self, name: str, raw: dict[str, int]) -> can.Message:
        data = self.by_name[name].encode(raw, scaling=False, strict=False)
        return can.Message(arbitration_id=self.ids[name], data=data, is_extended_id=False)

    def encode(self, msg: object) -> list[can.Message]:
        """The CAN frames of one message, in the order they must be sent."""
        if isinstance(msg, Sample):
            return self._sample(msg)
        if isinstance(msg, Hello):
            major, minor, patch = parse_fw_version(msg.fw_version)
            serial = check_int("serial", msg.serial, 0, 0xFFFFFFFF)
            boots = check_int("boot_count", msg.boot_count, 0, 0xFFFFFFFF)
            rate = check_int("rate_hz", msg.rate_hz, 0, 0xFFFF)
            self._last_anchor_us = None
            return [
                self._frame("HELLO", {"SERIAL": serial, "FW_MAJOR": major, "FW_MINOR": minor,
                                      "FW_PATCH": patch}),
                self._frame("HELLO_BOOT", {"BOOT_COUNT": boots, "RATE_HZ": rate,
                                           "SERIAL_LO": serial & 0xFFFF}),
            ]
        if isinstance(msg, CoeffWrite | CoeffReport):
            names = ("COEFF_BEGIN", "COEFF_DATA", "COEFF_COMMIT") if isinstance(msg, CoeffWrite) else (
                "REPORT_BEGIN", "REPORT_DATA", "REPORT_END")
            return self._coeff_set(msg, *names)
        if isinstance(msg, CoeffAck):
            version = check_int("version", msg.version, 0, CAN_VERSION_MAX)
            crc = check_int("crc", msg.crc, 0, 0xFFFFFFFF)
            return [self._frame("COEFF_ACK", {"CAL_VERSION": version, "CRC": crc})]
        if isinstance(msg, CoeffNak):
            version = check_int("version", msg.version, 0, CAN_VERSION_MAX)
            crc = check_int("crc", msg.crc, 0, 0xFFFFFFFF)
            reason = check_int("reason", msg.reason, 0, 255)
            return [self._frame("COEFF_NAK", {"REASON": reason, "CAL_VERSION": version, "CRC": crc})]
        if isinstance(msg, CoeffRead):
            return [can.Message(arbitration_id=self.ids["COEFF_READ"], data=b"", is_extended_id=False)]
        if isinstance(msg, HelloRequest):
            return [can.Message(arbitration_id=self.ids["HELLO_REQUEST"], data=b"", is_extended_id=False)]
        raise ProtocolError(f"{type(msg).__name__} has no CAN frames")

    def _sample(self, s: Sample) -> list[can.Message]:
        seq = check_int("seq", s.seq, 0, 0xFFFFFFFF)
        t_us = quantise("t_s", s.t_s, US_PER_S, 0, 2**48 - 1)
        g = [quantise(f"gyro_dps.{a}", s.gyro_dps[k], GYRO_PER_DPS, -(2**31), 2**31 - 1)
             for k, a in enumerate("xyz")]
        acc = [quantise(f"accel_g.{a}", s.accel_g[k], ACCEL_PER_G_CAN, -2048, 2047)
               for k, a in enumerate("xyz")]
        temp = quantise("temp_c", s.temp_c, TEMP_PER_C, -32768, 32767)
        seq16, seq4, t20 = seq & 0xFFFF, seq & 0xF, t_us & T20_MASK
        frames = []
        last = self._last_anchor_us
        if last is None or seq % ANCHOR_EVERY == 0 or not 0 <= t_us - last < ANCHOR_MAX_US:
            frames.append(self._frame("SAMPLE_TIME", {"SEQ": seq16, "T_US": t_us}))
            self._last_anchor_us = t_us
        frames.append(self._frame("SAMPLE_A", {"SEQ": seq16, "GYRO_X": g[0], "TEMP": temp}))
        frames.append(self._frame("SAMPLE_B", {"SEQ4": seq4, "T_HI": t20 >> 16, "GYRO_Y": g[1],
                                               "ACCEL_X": acc[0], "ACCEL_Y": acc[1]}))
        frames.append(self._frame("SAMPLE_C", {"SEQ4": seq4, "GYRO_Z": g[2], "ACCEL_Z": acc[2],
                                               "T_LO": t20 & 0xFFFF}))
        return frames

    def _coeff_set(self, msg: CoeffWrite | CoeffReport, begin: str, data: str, end: str) -> list[can.Message]:
        version = check_int("version", msg.version, 0, CAN_VERSION_MAX)
        terms = check_int("terms_id", msg.terms_id, 0, 0xFFFF)
        body = coeff_set_bytes(version, terms, msg.coeffs_dps)[7:]
        n = len(msg.coeffs_dps[0])
        frames = [self._frame(begin, {"CAL_VERSION": version, "TERMS_ID": terms, "N_TERMS": n})]
        words = struct.unpack(f"<{len(body) // 4}I", body)
        ver_lo = version & 0xFFFF
        frames += [self._frame(data, {"CHUNK": k, "CAL_VERSION_LO": ver_lo, "WORD": w})
                   for k, w in enumerate(words)]
        crc = coeff_set_crc(version, terms, msg.coeffs_dps)
        frames.append(self._frame(end, {"CAL_VERSION": version, "CRC": crc}))
        return frames
