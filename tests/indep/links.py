"""The unit's two links: a pty standing in for its UART, and a python-can bus for its CAN port.

Each link has ``send_*`` calls for the unit's messages and a reader thread that turns the host's
frames into events on a queue: ("hello_request",), ("read",), ("write", CoeffSet),
("write_failed", version, crc, reason) and, for a serial COEFF_WRITE whose n disagrees with its
length, nothing (it is counted and dropped, doc sec. 6).
"""

from __future__ import annotations

import os
import queue
import select
import struct
import threading
import tty

import numpy as np

from tests.indep import wire
from tests.indep.wire import CoeffSet, RxStats, SerialReceiver


class PtyLink:
    """The unit's UART as a pty: the daemon opens ``path`` with pyserial (baud is not emulated)."""

    kind = "serial"
    accel_lsb_g = 1e-4

    def __init__(self, events: queue.Queue) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo or line editing before the daemon opens it
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.events = events
        self.rx = SerialReceiver()
        self.out = bytearray()
        self.tx_dropped_bytes = 0
        self.tx_bytes = 0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._reader, daemon=True)
        self._thread.start()

    def describe(self) -> str:
        return self.path

    def stats(self) -> dict:
        return {**self.rx.stats.__dict__, "tx_bytes": self.tx_bytes,
                "tx_dropped_bytes": self.tx_dropped_bytes}

    # --- transmit -------------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        """Queue whole frames; a UART with nobody reading loses them (cap 64 KiB), never half frames."""
        with self._lock:
            if len(self.out) + len(data) > 65536:
                self.tx_dropped_bytes += len(data)
            else:
                self.out += data
            self.flush_locked()

    def flush_locked(self) -> None:
        while self.out:
            try:
                n = os.write(self.master, self.out)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.tx_dropped_bytes += len(self.out)
                self.out.clear()
                return
            self.tx_bytes += n
            del self.out[:n]

    def flush(self) -> None:
        with self._lock:
            self.flush_locked()

    def send_hello(self, serial: int, fw: tuple[int, int, int], boot: int, rate_hz: int) -> None:
        self._write(wire.frame(wire.HELLO, wire.hello_payload(serial, fw, boot, rate_hz)))

    def send_samples(self, seq0: int, t_us: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                     temp: np.ndarray, anchor_first: bool) -> None:
        del anchor_first  # serial carries the full time in every sample
        parts = [wire.frame(wire.SAMPLE, wire.sample_payload(seq0 + i, int(t_us[i]), gyro[i], accel[i],
                                                             float(temp[i]))) for i in range(len(t_us))]
        self._write(b"".join(parts))

    def send_ack(self, version: int, crc: int) -> None:
        self._write(wire.frame(wire.COEFF_ACK, struct.pack("<II", version, crc)))

    def send_nak(self, version: int, crc: int, reason: int) -> None:
        self._write(wire.frame(wire.COEFF_NAK, struct.pack("<IIB", version, crc, reason)))

    def send_report(self, cset: CoeffSet) -> None:
        self._write(wire.frame(wire.COEFF_REPORT, cset.encode()))

    # --- receive --------------------------------------------------------------------------------
    def _reader(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                continue
            for ftype, payload in self.rx.feed(data):
                self._dispatch(ftype, payload)

    def _dispatch(self, ftype: int, payload: bytes) -> None:
        if ftype == wire.HELLO_REQUEST:
            self.events.put(("hello_request",))
        elif ftype == wire.COEFF_READ:
            self.events.put(("read",))
        elif ftype == wire.COEFF_WRITE:
            try:
                self.events.put(("write", CoeffSet.decode(payload)))
            except ValueError:
                self.rx.stats.length_errors += 1  # n disagrees with L: dropped, no NAK
        # unit->host types arriving here (our own frames never loop back on a pty) are ignored

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


def pack_bits(fields: list[tuple[int, int, int]]) -> bytes:
    """Intel-order signals (start bit, length, raw value; negatives two's complement) into 8 bytes."""
    word = 0
    for start, length, value in fields:
        word |= (value & ((1 << length) - 1)) << start
    return word.to_bytes(8, "little")


def unpack_bits(data: bytes, start: int, length: int) -> int:
    return (int.from_bytes(data.ljust(8, b"\0"), "little") >> start) & ((1 << length) - 1)


# CAN functions (id = 0x100 + (function << 4) + node_id)
F_HELLO_REQUEST, F_HELLO, F_HELLO_BOOT, F_ACK, F_NAK, F_READ = 0, 1, 2, 3, 4, 5
F_BEGIN, F_DATA, F_COMMIT, F_REPORT_BEGIN, F_REPORT_DATA, F_REPORT_END = 6, 7, 8, 9, 10, 11
F_SAMPLE_TIME, F_SAMPLE_A, F_SAMPLE_B, F_SAMPLE_C = 12, 13, 14, 15
HOST_DLC = {F_HELLO_REQUEST: 0, F_READ: 0, F_BEGIN: 8, F_DATA: 8, F_COMMIT: 8}
UNIT_FUNCTIONS = {F_HELLO, F_HELLO_BOOT, F_ACK, F_NAK, F_REPORT_BEGIN, F_REPORT_DATA, F_REPORT_END,
                  F_SAMPLE_TIME, F_SAMPLE_A, F_SAMPLE_B, F_SAMPLE_C}


class CanTransfer:
    """COEFF_BEGIN / DATA / COMMIT reassembly, doc sec. 3 "Multi-frame transfers" rules 1-3."""

    def __init__(self, stats: RxStats) -> None:
        self.stats = stats
        self.open: tuple[int, int, int] | None = None  # version, terms_id, n
        self.chunks: dict[int, int] = {}
        self.broken = False

    def begin(self, data: bytes) -> None:
        if self.open is not None:
            self.stats.incomplete += 1  # abandoned
        self.open = (unpack_bits(data, 0, 32), unpack_bits(data, 32, 16), unpack_bits(data, 48, 8))
        self.chunks, self.broken = {}, False

    def data(self, data: bytes) -> None:
        chunk, ver_lo, word = unpack_bits(data, 0, 16), unpack_bits(data, 16, 16), unpack_bits(data, 32, 32)
        if self.open is None or ver_lo != self.open[0] & 0xFFFF:
            self.stats.garbage_bytes += 8  # a stray chunk: counted and ignored (rule 2)
            return
        if chunk >= 6 * min(self.open[2], wire.MAX_TERMS) or chunk in self.chunks:
            self.broken = True
            return
        self.chunks[chunk] = word

    def commit(self, data: bytes) -> tuple:
        """The event for the unit: ("write", set) or ("write_failed", version, crc, reason)."""
        version, crc = unpack_bits(data, 0, 32), unpack_bits(data, 32, 32)
        opened, self.open = self.open, None
        if opened is None:
            return ("write_failed", version, crc, wire.NAK_INCOMPLETE)
        bversion, tid, n = opened
        if version != bversion:
            return ("write_failed", version, crc, wire.NAK_INCOMPLETE)
        if n > wire.MAX_TERMS:
            return ("write_failed", version, crc, wire.NAK_BAD_LENGTH)
        if self.broken or sorted(self.chunks) != list(range(6 * n)):
            return ("write_failed", version, crc, wire.NAK_INCOMPLETE)
        body = b"".join(self.chunks[k].to_bytes(4, "little") for k in range(6 * n))
        encoded = struct.pack("<IHB", version, tid, n) + body
        if wire.crc32(encoded) != crc:
            return ("write_failed", version, crc, wire.NAK_BAD_CRC)
        return ("write", CoeffSet.decode(encoded))


class CanLink:
    """The unit's CAN port on a python-can bus (udp_multicast across processes), node ``node``."""

    kind = "can"
    accel_lsb_g = 1e-3

    def __init__(self, events: queue.Queue, node: int, bus_kwargs: dict) -> None:
        import can

        self._can = can
        self.node = node
        self.bus_kwargs = bus_kwargs
        self.bus = can.Bus(**bus_kwargs)
        self.events = events
        self.stats_rx = RxStats()
        self.transfer = CanTransfer(self.stats_rx)
        self.tx_frames = 0
        self.tx_errors = 0
        self.last_anchor_us: int | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._reader, daemon=True)
        self._thread.start()

    def describe(self) -> str:
        args = " ".join(f"{k}={v}" for k, v in self.bus_kwargs.items())
        return f"can {args} node={self.node}"

    def stats(self) -> dict:
        return {**self.stats_rx.__dict__, "tx_frames": self.tx_frames, "tx_errors": self.tx_errors}

    def _send(self, function: int, data: bytes) -> None:
        msg = self._can.Message(arbitration_id=0x100 + (function << 4) + self.node, data=data,
                                is_extended_id=False)
        try:
            self.bus.send(msg)
            self.tx_frames += 1
        except (self._can.CanError, OSError):
            self.tx_errors += 1

    def flush(self) -> None:
        pass

    def send_hello(self, serial: int, fw: tuple[int, int, int], boot: int, rate_hz: int) -> None:
        self._send(F_HELLO, pack_bits([(0, 32, serial), (32, 8, fw[0]), (40, 8, fw[1]), (48, 8, fw[2])]))
        self._send(F_HELLO_BOOT, pack_bits([(0, 32, boot), (32, 16, rate_hz), (48, 16, serial & 0xFFFF)]))
        self.last_anchor_us = None  # the next sample after any HELLO carries an anchor (sec. 6)

    def send_samples(self, seq0: int, t_us: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                     temp: np.ndarray, anchor_first: bool) -> None:
        if anchor_first:
            self.last_anchor_us = None
        for i in range(len(t_us)):
            seq, t = seq0 + i, int(t_us[i])
            gx, gy, gz = (wire.sat(float(v), 1e-6, 32) for v in gyro[i])
            ax, ay, az = (wire.sat(float(v), 1e-3, 12) for v in accel[i])
            tc = wire.sat(float(temp[i]), 0.01, 16)
            if self.last_anchor_us is None or seq % 256 == 0 or t - self.last_anchor_us >= 1_000_000:
                self._send(F_SAMPLE_TIME, pack_bits([(0, 16, seq), (16, 48, t)]))
                self.last_anchor_us = t
            self._send(F_SAMPLE_A, pack_bits([(0, 16, seq), (16, 32, gx), (48, 16, tc)]))
            self._send(F_SAMPLE_B, pack_bits([(0, 4, seq), (4, 4, t >> 16), (8, 32, gy), (40, 12, ax),
                                              (52, 12, ay)]))
            self._send(F_SAMPLE_C, pack_bits([(0, 4, seq), (4, 32, gz), (36, 12, az), (48, 16, t)]))

    def send_ack(self, version: int, crc: int) -> None:
        self._send(F_ACK, pack_bits([(0, 32, version), (32, 32, crc)]))

    def send_nak(self, version: int, crc: int, reason: int) -> None:
        self._send(F_NAK, pack_bits([(0, 8, reason), (8, 24, version), (32, 32, crc)]))

    def send_report(self, cset: CoeffSet) -> None:
        body = cset.encode()[7:]
        self._send(F_REPORT_BEGIN, pack_bits([(0, 32, cset.version), (32, 16, cset.terms_id),
                                              (48, 8, cset.n)]))
        for k in range(len(body) // 4):
            word = int.from_bytes(body[4 * k:4 * k + 4], "little")
            self._send(F_REPORT_DATA, pack_bits([(0, 16, k), (16, 16, cset.version & 0xFFFF),
                                                 (32, 32, word)]))
        self._send(F_REPORT_END, pack_bits([(0, 32, cset.version), (32, 32, cset.crc)]))

    def _reader(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(0.1)
            except (self._can.CanError, OSError, ValueError):
                continue
            if msg is None:
                continue
            self._dispatch(msg)

    def _dispatch(self, msg) -> None:
        st = self.stats_rx
        aid = msg.arbitration_id
        if (msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or not 0x100 <= aid <= 0x1FF
                or aid & 0xF != self.node):
            st.foreign_frames += 1
            return
        function = (aid - 0x100) >> 4
        if function in UNIT_FUNCTIONS:
            return  # a unit-side frame (ours looped back, or another unit's echo): not for us
        data = bytes(msg.data)
        if msg.dlc != HOST_DLC[function]:
            st.length_errors += 1
            return
        st.frames += 1
        if function == F_HELLO_REQUEST:
            self.events.put(("hello_request",))
        elif function == F_READ:
            self.events.put(("read",))
        elif function == F_BEGIN:
            self.transfer.begin(data)
        elif function == F_DATA:
            self.transfer.data(data)
        elif function == F_COMMIT:
            self.events.put(self.transfer.commit(data))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()
