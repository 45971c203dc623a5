"""CanDecoder: CAN frames in, messages out, reassembling samples, HELLO and coefficient transfers.

Like the serial FrameDecoder it is pure (no bus, no threads) and counts everything it rejects in a
DecoderStats. On CAN the bus already checks each frame with its own CRC-15, so the errors here are
lost or repeated parts: a SAMPLE whose A, B or C frame is missing, a coefficient chunk missing or
sent twice, a commit whose CRC-32 does not match what arrived. State is bounded: at most four partial
samples, one HELLO, one transfer in each direction.
"""

from __future__ import annotations

import binascii
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import can

from gyrocal.errors import ProtocolError
from gyrocal.protocol.messages import (
    ACCEL_PER_G_CAN,
    GYRO_PER_DPS,
    MAX_TERMS,
    TEMP_PER_C,
    US_PER_S,
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffTransferFailed,
    CoeffWrite,
    Hello,
    HelloRequest,
    NakReason,
    Sample,
    SampleConflict,
    coeff_set_crc,
)
from gyrocal.protocol.stats import DecoderStats

if TYPE_CHECKING:
    from gyrocal.protocol.can_codec import CanCodec

T20 = 1 << 20
MAX_PARTIALS = 4
"""Partial samples held at once; the oldest is dropped (and counted) beyond this."""
MAX_AGE = 6
"""A partial sample older than this many sample frames can no longer complete."""
TIME_TOL = 0.1
"""A sample's time may be this many sample periods from where its sequence number puts it."""
CLOCK_TOL = 0.01
"""... plus this share of the span since the last sample (a rate off by 1 %, over a gap)."""
REJECT_RESYNC = 50
"""Samples in a row whose time does not fit after which the sample state starts again (a clock jump)."""


def _raw_decoder(message: Any) -> Callable[[bytes], dict[str, int]]:
    """The raw signal values of a frame of ``message`` (a cantools Message), as ``decode_simple``
    gives them with ``decode_choices=False, scaling=False`` on data of the right length.

    For a plain message (no multiplexer, not a container) that is the union of cantools' compiled
    big- and little-endian bitstruct unpacks, which is what ``decode_simple`` computes below four
    layers of Python calls; called directly, a frame decodes ~3x faster (a .blf log holds three
    frames per sample). Anything else, or a cantools without these internals, takes the public call.
    """
    codecs = getattr(message, "_codecs", None)
    formats = codecs.get("formats") if isinstance(codecs, dict) else None
    plain = (formats is not None and not codecs.get("multiplexers") and not message.is_container
             and hasattr(formats, "big_endian") and hasattr(formats, "little_endian"))
    if not plain:
        return lambda data: message.decode_simple(data, decode_choices=False, scaling=False)
    big, little = formats.big_endian.unpack, formats.little_endian.unpack
    return lambda data: {**big(data), **little(data[::-1])}


@dataclass
class _Transfer:
    """A coefficient set being received: 6*n 32-bit words, each expected exactly once."""

    version: int
    terms_id: int
    n: int
    words: list[int | None] = field(default_factory=list)
    broken: bool = False

    def add(self, chunk: int, word: int) -> None:
        if chunk >= len(self.words) or self.words[chunk] is not None:
            self.broken = True  # out of range or duplicated
        else:
            self.words[chunk] = word

    def complete(self) -> bool:
        return not self.broken and all(w is not None for w in self.words)


class CanDecoder:
    """``feed(can.Message) -> list of messages`` for one node id; counters in ``.stats``.

    stats.frames counts CAN frames accepted, stats.bytes their data bytes. On the unit side a failed
    COEFF_COMMIT yields a CoeffTransferFailed, which the unit answers with a CoeffNak.
    """

    def __init__(self, codec: CanCodec | None = None, node_id: int = 0) -> None:
        if codec is None:
            from gyrocal.protocol.can_codec import CanCodec

            codec = CanCodec(node_id=node_id)
        self.node_id = codec.node_id
        self.stats = DecoderStats()
        self.mark_conflicts = False  # a log reader's: yield SampleConflict for a conflicting copy
        self._by_id: dict[int, tuple[Any, Any, int]] = {
            codec.ids[name]: (getattr(self, f"_on_{name.lower()}"), _raw_decoder(codec.by_name[name]),
                              codec.by_name[name].length)
            for name in codec.ids
        }
        self.reset()

    def reset(self) -> None:
        """Forget partial messages and seq/time state (e.g. after the bus reopened); keep counters."""
        self._partials: dict[int, list[Any]] = {}
        self._tick = 0
        self._anchor: tuple[int, int] | None = None
        self._last_seq: int | None = None
        self._last_t_us = 0
        self._last_values: tuple[int, ...] = ()
        self._dt_us = 0
        self._rejects = 0
        self._hello: dict[str, int] | None = None
        self._write: _Transfer | None = None
        self._report: _Transfer | None = None

    def feed(self, frame: can.Message) -> list[object]:
        """Accept one received CAN frame; return the messages it completes (usually none or one)."""
        st = self.stats
        entry = self._by_id.get(frame.arbitration_id)
        fd = bool(getattr(frame, "is_fd", False))
        if entry is None or frame.is_extended_id or frame.is_remote_frame or frame.is_error_frame or fd:
            fid = frame.arbitration_id
            # a remote, error, extended or CAN FD frame is never ours, whatever its id (protocol.md's
            # table: foreign_frames; the protocol is classic CAN. A remote frame on our id was counted as
            # an unknown type, and FD frames on our ids were decoded as the unit's samples: an outside
            # user's log of 4,746 of them gave an x constant of +273 deg/h)
            ours = not (frame.is_extended_id or frame.is_remote_frame or frame.is_error_frame or fd)
            if ours and 0x100 <= fid < 0x200 and fid & 0xF == self.node_id:
                st.unknown_types += 1
                st.garbage_bytes += len(frame.data)
            else:
                st.foreign_frames += 1
            return []
        handler, decode, length = entry
        data = bytes(frame.data)
        st.bytes += len(data)
        if len(data) != length:
            st.length_errors += 1
            return []
        st.frames += 1
        return handler(decode(data))

    # -- bulk decoding (readers.canbulk) -------------------------------------------------------
    def sample_state(self) -> tuple[int, int, int] | None:
        """(last seq, last unit time [us], sample period [us]) when the next complete A, B, C
        triple depends on nothing else: no partial sample, no pending anchor, a sample seen since
        the switch-on. None otherwise: then only ``feed`` knows what the next frames do."""
        if self._partials or self._anchor is not None or self._last_seq is None:
            return None
        return self._last_seq, self._last_t_us, self._dt_us

    def advance_samples(self, last_seq: int, last_t_us: int, dt_us: int, parts: int, anchors: int,
                        last_values: tuple[int, ...] = ()) -> None:
        """Take the state ``feed`` would have after a bulk decoder decoded, from ``sample_state``,
        consecutive in-order samples: ``parts`` SAMPLE_A/B/C frames and ``anchors`` SAMPLE_TIME
        frames (each 8 bytes, each anchor used by the sample after it); ``last_values``: the last
        sample's raw gx, gy, gz, ax, ay, az, temp and time [us], as ``_complete`` keeps them."""
        self._last_seq, self._last_t_us, self._dt_us = last_seq, last_t_us, dt_us
        self._last_values = last_values
        self._rejects = 0
        self._tick += parts
        self.stats.frames += parts + anchors
        self.stats.bytes += 8 * (parts + anchors)

    # -- samples -------------------------------------------------------------------------------
    def _on_sample_time(self, raw: dict[str, int]) -> list[object]:
        self._anchor = (raw["SEQ"], raw["T_US"])
        return []

    def _part(self, key: int, slot: int, value: tuple[int, ...]) -> list[object]:
        self._tick += 1
        parts = self._partials.get(key)
        if parts is not None and self._tick - parts[3] > MAX_AGE:
            self._drop_partial(key)  # too old to belong to this sample: it can never complete
            parts = None
        if parts is not None and parts[slot] is not None:
            if parts[slot] == value:
                return []  # the same frame twice: ignore the copy
            self._drop_partial(key)  # a different part in a filled slot: the old partial is dead
            parts = None
        if parts is None:
            for old in [k for k, p in self._partials.items() if self._tick - p[3] > MAX_AGE]:
                self._drop_partial(old)
            parts = self._partials[key] = [None, None, None, self._tick]
            while len(self._partials) > MAX_PARTIALS:
                self._drop_partial(next(iter(self._partials)))
        parts[slot] = value
        if parts[0] is None or parts[1] is None or parts[2] is None:
            return []
        del self._partials[key]
        return self._complete(parts[0], parts[1], parts[2])

    def _drop_partial(self, key: int) -> None:
        del self._partials[key]
        self.stats.incomplete += 1
        self.stats.resyncs += 1

    def _on_sample_a(self, raw: dict[str, int]) -> list[object]:
        return self._part(raw["SEQ"] & 0xF, 0, (raw["SEQ"], raw["GYRO_X"], raw["TEMP"]))

    def _on_sample_b(self, raw: dict[str, int]) -> list[object]:
        return self._part(raw["SEQ4"], 1, (raw["T_HI"], raw["GYRO_Y"], raw["ACCEL_X"], raw["ACCEL_Y"]))

    def _on_sample_c(self, raw: dict[str, int]) -> list[object]:
        return self._part(raw["SEQ4"], 2, (raw["GYRO_Z"], raw["ACCEL_Z"], raw["T_LO"]))

    def _complete(self, a: tuple[int, ...], b: tuple[int, ...], c: tuple[int, ...]) -> list[object]:
        st = self.stats
        seq16, gx, temp = a
        t_hi, gy, ax, ay = b
        gz, az, t_lo = c
        t20 = (t_hi << 16) | t_lo
        last = self._last_seq
        delta = 1
        if last is None:
            seq = seq16  # the high bits start at 0 when this decoder starts (docs/protocol.md)
        else:
            d = (seq16 - last) & 0xFFFF
            delta = d if d < 0x8000 else d - 0x10000  # signed steps since the previous sample
            seq = (last + delta) & 0xFFFFFFFF
        anchor = self._anchor
        anchored = anchor is not None and anchor[0] == seq16
        if anchored and anchor is not None:
            t_us = anchor[1]
            self._anchor = None
            if t_us & (T20 - 1) != t20:
                st.incomplete += 1  # the anchor and the sample disagree: do not guess
                st.resyncs += 1
                return []
        else:
            if anchor is not None and 0 < (seq16 - anchor[0]) & 0xFFFF < 0x8000:
                self._anchor = None  # its own sample was lost; never apply it to a later one
            if last is None:
                st.unanchored += 1
                return []
            t_est = self._last_t_us + delta * self._dt_us
            t_us = t_est + ((t20 - t_est + T20 // 2) % T20) - T20 // 2
        if last is not None and self._dt_us > 0 and not self._plausible(t_us, delta, anchored):
            # a time that does not follow from the sequence number: frames on our ids that are not the
            # unit's (3000 random SAMPLE_A/B/C frames made samples stamped 366 s into an 83 s session
            # and 69,009 lost samples of 17,000: an integrator's fault campaign), or a unit clock that
            # jumped. Dropped and counted; after REJECT_RESYNC in a row the sample state starts again
            # from the next anchored sample, as at switch-on (a clock that really jumped)
            st.implausible += 1
            self._rejects += 1
            if self._rejects >= REJECT_RESYNC:
                self._last_seq, self._anchor, self._rejects = None, None, 0
                st.resyncs += 1
            return []
        self._rejects = 0
        values = (gx, gy, gz, ax, ay, az, temp, t_us)
        if last is not None and delta == 0:
            # the previous sample again: a copy is never a second sample, and one with other values is
            # another sender on our ids
            if values == self._last_values:
                st.repeated += 1
                return []
            st.conflicting += 1
            return [SampleConflict(seq)] if self.mark_conflicts else []
        if last is not None and delta != 1:
            st.seq_gaps += 1
            if delta > 1:
                st.lost_samples += delta - 1
        elif last is not None and t_us > self._last_t_us:
            self._dt_us = t_us - self._last_t_us
        if last is None or delta > 0:  # a late older sample is passed on but does not move the state
            self._last_seq = seq
            self._last_t_us = t_us
            self._last_values = values
        return [Sample(seq, t_us / US_PER_S, (gx / GYRO_PER_DPS, gy / GYRO_PER_DPS, gz / GYRO_PER_DPS),
                       (ax / ACCEL_PER_G_CAN, ay / ACCEL_PER_G_CAN, az / ACCEL_PER_G_CAN), temp / TEMP_PER_C)]

    def _plausible(self, t_us: int, delta: int, anchored: bool) -> bool:
        """Whether a sample ``delta`` sequence steps from the last one, stamped ``t_us``, lies within
        TIME_TOL sample periods (plus CLOCK_TOL of the span) of where the last period puts it; an
        unanchored one also within half the 20-bit time's wrap (protocol.md: exact only there)."""
        span = delta * self._dt_us
        if not anchored and abs(span) >= T20 // 2:
            return False  # the 20-bit time cannot be placed that far from the estimate: wait for an anchor
        return abs(t_us - (self._last_t_us + span)) <= self._dt_us * TIME_TOL + CLOCK_TOL * abs(span)

    # -- HELLO ---------------------------------------------------------------------------------
    def _on_hello(self, raw: dict[str, int]) -> list[object]:
        if self._hello is not None:
            self.stats.incomplete += 1
        self._hello = raw
        return []

    def _on_hello_boot(self, raw: dict[str, int]) -> list[object]:
        h, self._hello = self._hello, None
        if h is None or h["SERIAL"] & 0xFFFF != raw["SERIAL_LO"]:
            self.stats.incomplete += 1
            return []
        self.reset()  # a new switch-on: seq, time and partial transfers restart
        return [Hello(h["SERIAL"], f"{h['FW_MAJOR']}.{h['FW_MINOR']}.{h['FW_PATCH']}", raw["BOOT_COUNT"],
                      raw["RATE_HZ"])]

    # -- single-frame control ------------------------------------------------------------------
    def _on_coeff_ack(self, raw: dict[str, int]) -> list[object]:
        return [CoeffAck(raw["CAL_VERSION"], raw["CRC"])]

    def _on_coeff_nak(self, raw: dict[str, int]) -> list[object]:
        code = raw["REASON"]
        reason = NakReason(code) if code in NakReason._value2member_map_ else code
        return [CoeffNak(raw["CAL_VERSION"], raw["CRC"], reason)]

    def _on_coeff_read(self, raw: dict[str, int]) -> list[object]:
        return [CoeffRead()]

    def _on_hello_request(self, raw: dict[str, int]) -> list[object]:
        return [HelloRequest()]

    # -- coefficient transfers -----------------------------------------------------------------
    def _begin(self, old: _Transfer | None, raw: dict[str, int]) -> _Transfer:
        if old is not None:
            self.stats.incomplete += 1
        n = raw["N_TERMS"]
        t = _Transfer(raw["CAL_VERSION"], raw["TERMS_ID"], n, [None] * (6 * min(n, MAX_TERMS)))
        if n > MAX_TERMS:
            self.stats.length_errors += 1
            t.broken = True
        return t

    def _data(self, t: _Transfer | None, raw: dict[str, int]) -> None:
        if t is None or raw["CAL_VERSION_LO"] != t.version & 0xFFFF:
            self.stats.incomplete += 1  # a stray chunk of no open transfer
            return
        t.add(raw["CHUNK"], raw["WORD"])

    def _finish(self, t: _Transfer | None, raw: dict[str, int]) -> tuple[object | None, int]:
        """(the set as CoeffWrite, 0) or (None, NakReason) for a commit closing transfer t."""
        if t is not None and t.n > MAX_TERMS and t.version == raw["CAL_VERSION"]:
            return None, NakReason.BAD_LENGTH  # BEGIN announced more terms than a set can have
        if t is None or t.version != raw["CAL_VERSION"] or not t.complete():
            self.stats.incomplete += 1
            return None, NakReason.INCOMPLETE
        body = struct.pack(f"<{6 * t.n}I", *t.words)
        # the CRC first, over the bytes as they came (doc sec. 6 order): a corrupt transfer is
        # BAD_CRC whatever its floats decode to; only an intact one can be judged on its values
        if binascii.crc32(struct.pack("<IHB", t.version, t.terms_id, t.n) + body) != raw["CRC"]:
            self.stats.crc_errors += 1
            return None, NakReason.BAD_CRC
        flat = struct.unpack(f"<{3 * t.n}d", body)
        rows = (flat[: t.n], flat[t.n : 2 * t.n], flat[2 * t.n :])
        try:
            coeff_set_crc(t.version, t.terms_id, rows)
        except ProtocolError:  # NaN/Inf under a valid CRC: counted and dropped
            self.stats.bad_values += 1
            return None, NakReason.OUT_OF_RANGE
        return CoeffWrite(t.version, t.terms_id, rows), 0

    def _on_coeff_begin(self, raw: dict[str, int]) -> list[object]:
        self._write = self._begin(self._write, raw)
        return []

    def _on_coeff_data(self, raw: dict[str, int]) -> list[object]:
        self._data(self._write, raw)
        return []

    def _on_coeff_commit(self, raw: dict[str, int]) -> list[object]:
        t, self._write = self._write, None
        msg, reason = self._finish(t, raw)
        if msg is None:
            return [CoeffTransferFailed(raw["CAL_VERSION"], raw["CRC"], reason)]
        return [msg]

    def _on_report_begin(self, raw: dict[str, int]) -> list[object]:
        self._report = self._begin(self._report, raw)
        return []

    def _on_report_data(self, raw: dict[str, int]) -> list[object]:
        self._data(self._report, raw)
        return []

    def _on_report_end(self, raw: dict[str, int]) -> list[object]:
        t, self._report = self._report, None
        msg, _ = self._finish(t, raw)
        if not isinstance(msg, CoeffWrite):
            return []  # counted; the host times out and sends COEFF_READ again
        return [CoeffReport(msg.version, msg.terms_id, msg.coeffs_dps)]
