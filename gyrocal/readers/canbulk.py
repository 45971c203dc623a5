"""Bulk DBC decoding: the unit's SAMPLE frames of a recording to sample blocks with numpy.

``CanRecording`` feeds a recording's frames to the live link's ``CanDecoder`` one by one. For a
long .blf that is the slow part, so here the frames arrive as arrays (``readers.blf.BlfFrames``)
and the common case is decoded in bulk: a stretch of complete SAMPLE_A, SAMPLE_B, SAMPLE_C triples
(each maybe preceded by its SAMPLE_TIME anchor) whose seq steps by one and whose 20-bit time
unwraps without doubt. Everything else (HELLO, coefficient reports, a missing or repeated part, a
seq gap, an anchor that disagrees, error and CAN FD frames, ...) goes through ``CanDecoder.feed``
in file order, and the decoder's state is handed over at each boundary (``sample_state`` and
``advance_samples``), so the samples and every counter are the ones ``feed`` alone gives.

The bit positions, signedness and scales come from the DBC (cantools). The scales must be the
ones the decoder applies (``GYRO_PER_DPS`` ...), else nothing is decoded in bulk: the two paths
must never disagree. A value is raw / (1 / scale), as the decoder computes it, so both give the
same float64 bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from gyrocal.daemon.ring import SAMPLE_DTYPE
from gyrocal.protocol.can_codec import CanCodec
from gyrocal.protocol.can_reassembly import CLOCK_TOL, T20, TIME_TOL, CanDecoder
from gyrocal.protocol.messages import ACCEL_PER_G_CAN, GYRO_PER_DPS, TEMP_PER_C, US_PER_S
from gyrocal.readers.blf import FLAG_EXT, FLAG_REMOTE, BlfFrames

MAX_RUN = 1 << 16
"""Samples decoded per bulk step (bounds the temporary arrays)."""
CODES = {"SAMPLE_TIME": 1, "SAMPLE_A": 2, "SAMPLE_B": 3, "SAMPLE_C": 4}
SCALED = {"GYRO_X": GYRO_PER_DPS, "GYRO_Y": GYRO_PER_DPS, "GYRO_Z": GYRO_PER_DPS, "ACCEL_X": ACCEL_PER_G_CAN,
          "ACCEL_Y": ACCEL_PER_G_CAN, "ACCEL_Z": ACCEL_PER_G_CAN, "TEMP": TEMP_PER_C}
"""Signal -> the counts per unit that CanDecoder divides by; the DBC's scale must be its inverse."""
UNSCALED = ("SEQ", "T_US", "SEQ4", "T_HI", "T_LO")


class _Signal:
    """One little-endian DBC signal of an 8-byte frame, extracted from uint64 payloads."""

    def __init__(self, sig: Any) -> None:
        self.name, self.start, self.length, self.signed = sig.name, sig.start, sig.length, sig.is_signed
        self.scale, self.offset = sig.scale, sig.offset
        self.per_unit = float(round(1.0 / sig.scale))
        """Counts per unit (1 / the DBC's scale, an integer): value = raw / per_unit, as CanDecoder."""

    def raw(self, payload: np.ndarray) -> np.ndarray:
        v = ((payload >> np.uint64(self.start)) & np.uint64((1 << self.length) - 1)).astype(np.int64)
        if self.signed:
            v = np.where(v >= 1 << (self.length - 1), v - (1 << self.length), v)
        return v


def sample_signals(codec: CanCodec) -> dict[str, dict[str, _Signal]] | None:
    """The SAMPLE_* messages' signals by message name, or None if bulk decoding cannot match the
    decoder for this DBC (a big-endian or multiplexed signal, another length, or a scale or offset
    other than the decoder's)."""
    out: dict[str, dict[str, _Signal]] = {}
    for name in CODES:
        msg = codec.by_name.get(name)
        if msg is None or msg.length != 8 or msg.is_multiplexed():
            return None
        sigs = {}
        for sig in msg.signals:
            if sig.byte_order != "little_endian" or sig.offset != 0:
                return None
            if sig.name in SCALED:
                inverse = 1.0 / sig.scale
                if round(inverse) != SCALED[sig.name] or abs(inverse - round(inverse)) > 1e-9 * inverse:
                    return None
            elif sig.name not in UNSCALED or sig.scale != 1:
                return None
            sigs[sig.name] = _Signal(sig)
        out[name] = sigs
    need = {"SAMPLE_TIME": {"SEQ", "T_US"}, "SAMPLE_A": {"SEQ", "GYRO_X", "TEMP"},
            "SAMPLE_B": {"SEQ4", "T_HI", "GYRO_Y", "ACCEL_X", "ACCEL_Y"},
            "SAMPLE_C": {"SEQ4", "GYRO_Z", "ACCEL_Z", "T_LO"}}
    if any(not need[m] <= set(out[m]) for m in need):
        return None
    return out


class BulkCanDecoder:
    """Decode a recording's frame arrays with ``decoder``, in bulk where it can (module docstring).

    ``route(frame)`` is the recording's per-frame path (error and host frames counted, the rest fed
    to ``decoder``); it takes a ``can.Message`` and yields decoded messages. ``counts`` receives
    ``host_frames`` counted in bulk.
    """

    def __init__(self, codec: CanCodec, decoder: CanDecoder, accept: frozenset[int] | None,
                 route: Callable[[Any], Iterable[object]], counts: dict[str, int],
                 host_ids: frozenset[int] | None = None) -> None:
        self.codec, self.decoder, self.accept, self.route, self.counts = codec, decoder, accept, route, counts
        self.host_ids = host_ids
        self.signals = sample_signals(codec)
        self.known = np.array(sorted(codec.ids.values()), dtype=np.uint32)
        self.bulk_samples = 0

    def _message(self, frames: BlfFrames, i: int) -> Any:
        msg = frames.special.get(i)
        if msg is not None:
            return msg
        from can import Message

        fl, n = int(frames.flags[i]), int(frames.length[i])
        return Message(arbitration_id=int(frames.arb_id[i]), is_extended_id=bool(fl & FLAG_EXT),
                       is_remote_frame=bool(fl & FLAG_REMOTE),
                       data=int(frames.payload[i]).to_bytes(8, "little")[:n])

    def messages(self, frames: BlfFrames) -> Iterator[Any]:
        """Decoded unit messages and SAMPLE_DTYPE blocks (rx = 0), in file order."""
        n = len(frames)
        ids, flags = frames.arb_id, frames.flags
        ext, remote = (flags & FLAG_EXT) != 0, (flags & FLAG_REMOTE) != 0
        special = np.zeros(n, dtype=bool)
        special[np.fromiter(frames.special, dtype=np.int64, count=len(frames.special))] = True
        st = self.decoder.stats
        if self.accept is None:
            host = np.zeros(n, dtype=bool)
        else:
            accepted = np.isin(ids, np.array(sorted(self.accept), dtype=np.uint32))
            if self.host_ids is not None:
                to_host = np.isin(ids, np.array(sorted(self.host_ids), dtype=np.uint32))
            else:
                to_host = (ids >> 8) == 1
            host = ~special & ~accepted & ~ext & to_host
        self.counts["host_frames"] = self.counts.get("host_frames", 0) + int(host.sum())
        to_decoder = ~special & ~host
        known = to_decoder & np.isin(ids, self.known) & ~ext & ~remote
        # frames the decoder only counts (CanDecoder.feed's first branch): no state, any order
        only_counted = to_decoder & ~known
        node = self.decoder.node_id
        unknown = only_counted & ~ext & ~remote & (ids >= 0x100) & (ids < 0x200) & ((ids & 0xF) == node)
        st.unknown_types += int(unknown.sum())
        st.garbage_bytes += int(frames.length[unknown].sum())
        st.foreign_frames += int((only_counted & ~unknown).sum())
        order = np.flatnonzero(special | known)
        if self.signals is None:
            for i in order:
                yield from self.route(self._message(frames, int(i)))
            return
        yield from self._walk(frames, order)

    def _walk(self, frames: BlfFrames, order: np.ndarray) -> Iterator[Any]:
        """The ordered frames: stretches of regular triples in bulk, the rest through ``route``."""
        sigs = self.signals
        assert sigs is not None
        ids = frames.arb_id[order]
        pay = frames.payload[order]
        plain = (frames.length[order] == 8) & ~np.isin(order, np.fromiter(frames.special, dtype=np.int64))
        code = np.zeros(order.size, dtype=np.int8)
        for name, c in CODES.items():
            code[plain & (ids == self.codec.ids[name])] = c
        key = np.full(order.size, -1, dtype=np.int64)
        for name, sig in (("SAMPLE_A", "SEQ"), ("SAMPLE_B", "SEQ4"), ("SAMPLE_C", "SEQ4")):
            m = code == CODES[name]
            key[m] = sigs[name][sig].raw(pay[m]) & 0xF
        m_t = code == 1
        t_seq = np.full(order.size, -1, dtype=np.int64)
        t_seq[m_t] = sigs["SAMPLE_TIME"]["SEQ"].raw(pay[m_t])
        a_seq = np.full(order.size, -2, dtype=np.int64)
        m_a = code == 2
        a_seq[m_a] = sigs["SAMPLE_A"]["SEQ"].raw(pay[m_a])
        s = order.size
        start = np.zeros(s, dtype=bool)
        if s >= 3:
            start[: s - 2] = ((code[: s - 2] == 2) & (code[1: s - 1] == 3) & (code[2:] == 4)
                              & (key[: s - 2] == key[1: s - 1]) & (key[1: s - 1] == key[2:]))
        tri = np.flatnonzero(start)
        anch = np.zeros(tri.size, dtype=bool)
        ok = tri > 0
        anch[ok] = (code[tri[ok] - 1] == 1) & (t_seq[tri[ok] - 1] == a_seq[tri[ok]])
        bstart, bend = tri - anch, tri + 3
        cuts = np.flatnonzero(bend[:-1] != bstart[1:]) + 1
        stretch_end = np.append(cuts, tri.size)[np.searchsorted(cuts, np.arange(tri.size), side="right")]
        p, k = 0, 0
        route, decoder = self.route, self.decoder
        while p < s:
            if k < tri.size and bstart[k] == p:
                kend = int(stretch_end[k])
                while k < kend:
                    state = decoder.sample_state()
                    if state is not None:
                        done, block = self._bulk(order, pay, tri[k:min(kend, k + MAX_RUN)],
                                                 anch[k:min(kend, k + MAX_RUN)], state)
                        if done:
                            yield block
                            k += done
                            continue
                    for q in range(int(bstart[k]), int(bend[k])):
                        yield from route(self._message(frames, int(order[q])))
                    k += 1
                p = int(bend[kend - 1])
            else:
                yield from route(self._message(frames, int(order[p])))
                p += 1

    def _bulk(self, order: np.ndarray, pay: np.ndarray, tri: np.ndarray, anch: np.ndarray,
              state: tuple[int, int, int]) -> tuple[int, np.ndarray | None]:
        """Decode the longest prefix of these triples that ``feed`` would decode without a doubt,
        from the decoder's ``state``; returns (triples decoded, their SAMPLE_DTYPE block)."""
        sa, sb, sc, stime = (self.signals[m] for m in ("SAMPLE_A", "SAMPLE_B", "SAMPLE_C", "SAMPLE_TIME"))
        last_seq, last_t, dt0 = state
        pa, pb, pc = pay[tri], pay[tri + 1], pay[tri + 2]
        seq16 = sa["SEQ"].raw(pa)
        prev16 = np.concatenate(([last_seq & 0xFFFF], seq16[:-1]))
        seq_ok = ((seq16 - prev16) & 0xFFFF) == 1
        t20 = (sb["T_HI"].raw(pb) << 16) | sc["T_LO"].raw(pc)
        ta = np.zeros(tri.size, dtype=np.int64)
        ta[anch] = stime["T_US"].raw(pay[tri[anch] - 1])
        anchor_ok = ~anch | ((ta & (T20 - 1)) == t20)
        # candidate times: unwrap the 20-bit time forward from the last time or the last anchor
        prev20 = np.concatenate(([last_t & (T20 - 1)], t20[:-1]))
        c = np.cumsum(np.where(anch, 0, (t20 - prev20) & (T20 - 1)))
        idx = np.maximum.accumulate(np.where(anch, np.arange(tri.size), -1))
        base = np.where(idx < 0, last_t, ta[np.maximum(idx, 0)] - c[np.maximum(idx, 0)])
        t = base + c
        t_prev = np.concatenate(([last_t], t[:-1]))
        step = t - t_prev
        dt_prev = np.concatenate(([dt0], step[:-1]))
        off = t - (t_prev + dt_prev)  # the decoder's estimate is t_prev + the last period
        unwrap_ok = anch | ((off >= -(T20 // 2)) & (off < T20 // 2))
        # feed's plausibility rule for one step (CanDecoder._plausible with delta 1)
        plausible = (dt_prev <= 0) | (np.abs(off) <= dt_prev * (TIME_TOL + CLOCK_TOL))
        good = seq_ok & anchor_ok & (step > 0) & unwrap_ok & plausible
        bad = np.flatnonzero(~good)
        m = int(bad[0]) if bad.size else tri.size
        m = min(m, 0xFFFFFFFF - last_seq)  # a u32 seq wrap goes through feed
        if m <= 0:
            return 0, None
        block = np.zeros(m, dtype=SAMPLE_DTYPE)
        block["seq"] = last_seq + 1 + np.arange(m)
        block["t"] = t[:m] / float(US_PER_S)
        for col, frame, sig in (("wx", pa, sa["GYRO_X"]), ("wy", pb, sb["GYRO_Y"]), ("wz", pc, sc["GYRO_Z"]),
                                ("ax", pb, sb["ACCEL_X"]), ("ay", pb, sb["ACCEL_Y"]),
                                ("az", pc, sc["ACCEL_Z"]), ("temp", pa, sa["TEMP"])):
            block[col] = sig.raw(frame[:m]) / sig.per_unit
        anchors = int(anch[:m].sum())
        last = tuple(int(sig.raw(frame[m - 1:m])[0]) for frame, sig in (
            (pa, sa["GYRO_X"]), (pb, sb["GYRO_Y"]), (pc, sc["GYRO_Z"]), (pb, sb["ACCEL_X"]),
            (pb, sb["ACCEL_Y"]), (pc, sc["ACCEL_Z"]), (pa, sa["TEMP"]))) + (int(t[m - 1]),)
        self.decoder.advance_samples(last_seq + m, int(t[m - 1]), int(step[m - 1]), 3 * m, anchors, last)
        self.bulk_samples += m
        return m, block
