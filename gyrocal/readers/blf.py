"""A batched reader of Vector's BLF container format: the CAN frames of a .blf as numpy arrays.

Why our own: python-can's ``can.BLFReader`` builds one ``can.Message`` per frame in Python, and at
three frames per IMU sample that caps a .blf read near 45,000 samples/s. Here the file is cut into
its objects with numpy, and only what is unusual becomes a ``can.Message``.

The layout, as python-can's can/io/blf.py reads it (all little-endian; no official specification,
python-can follows Toby Lorenz' vector_blf):

- file header: ``"LOGG"``, header size (u32), ..., padded to that size (144 bytes from python-can);
- then top-level objects, each a 16-byte base header ``"LOBJ"``, header size (u16), header
  version (u16), object size (u32, base header included), object type (u32), followed by
  ``object size % 4`` padding bytes. Only LOG_CONTAINER (type 10) objects matter at the top: after
  the base header, compression method (u16; 0 none, 2 zlib), 6 bytes, uncompressed size (u32),
  4 bytes, then the (compressed) data;
- the containers' data, concatenated, is a stream of objects (an object may start in one container
  and end in the next), each located at the first ``"LOBJ"`` within 4 bytes of where the previous
  one ended. After the base header comes header v1 (flags u32, client index u16, object version
  u16, timestamp u64: 16 bytes) or v2 (24 bytes: flags u32, timestamp status u8, 1 byte, object
  version u16, timestamp u64, original timestamp u64); the flags say 10 us (1) or 1 ns (2) ticks;
- CAN_MESSAGE (1) and CAN_MESSAGE2 (86): channel u16, flags u8 (0x80 remote, 0x01 tx), dlc u8,
  id u32 (bit 31: extended), 8 data bytes; CAN_FD_MESSAGE (100), CAN_FD_MESSAGE_64 (101) and
  CAN_ERROR_EXT (73) are read object by object into the ``can.Message`` python-can would give.
  Other objects (markers, statistics, ...) are not CAN frames: counted in ``other_objects``.

Batching: where consecutive objects have the same base header (same type, size and header
version) at a fixed stride, they are read as one numpy structured array, after checking the
``"LOBJ"`` magic of every one of them; anything else is walked object by object.

What is never believed (python-can raises on some of these and returns half-decompressed data on
others): a container whose zlib stream fails or ends early, or whose size disagrees with its
header (``corrupt_containers``); a top-level object cut off by the end of the file
(``truncated_containers``); an object cut by a dropped container or the end of the data
(``cut_objects``); bytes between objects where no valid header starts (``garbage_bytes``). After a
dropped container the reader resynchronises at the next plausible object header.

Frame timestamps are not read: gyrocal's samples carry the unit's own time.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gyrocal.errors import LogFormatError

FILE_HEADER = struct.Struct("<4sL")
BASE = struct.Struct("<4sHHLL")
CONTAINER = struct.Struct("<H6xL4x")
CAN_MSG = struct.Struct("<HBBL8s")
CAN_FD_MSG = struct.Struct("<HBBLLBBB5x64s")
CAN_FD_MSG_64 = struct.Struct("<BBBBLLLLLLLHBBL")
CAN_ERROR_EXT = struct.Struct("<HHLBBBxLLH2x8s")

LOBJ = b"LOBJ"
T_CAN_MESSAGE, T_LOG_CONTAINER, T_CAN_ERROR_EXT, T_CAN_MESSAGE2 = 1, 10, 73, 86
T_CAN_FD_MESSAGE, T_CAN_FD_MESSAGE_64 = 100, 101
CLASSIC = (T_CAN_MESSAGE, T_CAN_MESSAGE2)
SPECIAL = (T_CAN_ERROR_EXT, T_CAN_FD_MESSAGE, T_CAN_FD_MESSAGE_64)
HEADER_BYTES = {1: 16, 2: 24}
"""Object header version -> its bytes after the 16-byte base header (python-can's structs)."""
CAN_MSG_EXT = 0x80000000
REMOTE_FLAG = 0x80
PIECE_BYTES = 1 << 24
"""Decompressed container data parsed at once (16 MiB, ~350,000 classic frames)."""
MAX_OBJECT = 1 << 24
"""An inner object bigger than this (16 MiB) is taken as a damaged header, not believed."""

FLAG_EXT, FLAG_REMOTE = 1, 2


@dataclass
class BlfFrames:
    """The CAN frames of a .blf in file order.

    ``arb_id`` (uint32, the 29 id bits), ``flags`` (uint8: FLAG_EXT, FLAG_REMOTE), ``length``
    (int16: len(data) as python-can gives it: 0 for a remote frame, else min(dlc, 8)) and ``payload``
    (uint64: the 8 data bytes, little-endian) describe classic CAN_MESSAGE/CAN_MESSAGE2 frames.
    ``special`` maps a frame's index to the ``can.Message`` python-can builds for the other frame
    objects (error frames, CAN FD); their rows in the arrays are placeholders.
    ``dropped`` counts what was not believed, by reason (see the module docstring).
    """

    arb_id: np.ndarray
    flags: np.ndarray
    length: np.ndarray
    payload: np.ndarray
    special: dict[int, Any] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    other_objects: int = 0
    containers: int = 0

    def __len__(self) -> int:
        return int(self.arb_id.size)


def _classic_dtype(stride: int, version: int) -> np.dtype:
    """One classic CAN object at ``stride`` bytes: its base header and CAN_MSG fields."""
    p = 16 + HEADER_BYTES[version]
    return np.dtype({"names": ["sig", "hsize", "hver", "osize", "otype", "flags", "dlc", "id", "data"],
                     "formats": ["<u4", "<u2", "<u2", "<u4", "<u4", "u1", "u1", "<u4", "<u8"],
                     "offsets": [0, 4, 6, 8, 12, p + 2, p + 3, p + 4, p + 8],
                     "itemsize": stride})


class _Builder:
    """Collects frames, as numpy pieces (runs) and single objects, in file order."""

    def __init__(self) -> None:
        self.pieces: list[tuple[np.ndarray, ...]] = []
        self.single: list[tuple[int, int, int, int]] = []  # (id, flags, length, payload)
        self.special: dict[int, Any] = {}
        self.n = 0

    def flush(self) -> None:
        if self.single:
            a = np.array(self.single, dtype=np.uint64).reshape(-1, 4)
            self.pieces.append((a[:, 0].astype(np.uint32), a[:, 1].astype(np.uint8),
                                a[:, 2].astype(np.int16), a[:, 3]))
            self.single = []

    def run(self, rec: np.ndarray) -> None:
        """A run of classic CAN objects (a structured array of ``_classic_dtype``)."""
        self.flush()
        raw_id = rec["id"]
        remote = (rec["flags"] & REMOTE_FLAG) != 0
        flags = np.where((raw_id & CAN_MSG_EXT) != 0, FLAG_EXT, 0).astype(np.uint8)
        flags |= np.where(remote, FLAG_REMOTE, 0).astype(np.uint8)
        length = np.where(remote, 0, np.minimum(rec["dlc"], 8)).astype(np.int16)
        self.pieces.append(((raw_id & 0x1FFFFFFF).astype(np.uint32), flags, length, rec["data"].copy()))
        self.n += rec.size

    def classic(self, raw_id: int, can_flags: int, dlc: int, data: bytes) -> None:
        remote = bool(can_flags & REMOTE_FLAG)
        flags = (FLAG_EXT if raw_id & CAN_MSG_EXT else 0) | (FLAG_REMOTE if remote else 0)
        self.single.append((raw_id & 0x1FFFFFFF, flags, 0 if remote else min(dlc, 8),
                            int.from_bytes(data, "little")))
        self.n += 1

    def message(self, msg: Any) -> None:
        self.special[self.n] = msg
        self.single.append((msg.arbitration_id, 0, 0, 0))
        self.n += 1

    def result(self) -> tuple[np.ndarray, ...]:
        self.flush()
        if not self.pieces:
            return tuple(np.zeros(0, t) for t in (np.uint32, np.uint8, np.int16, np.uint64))
        return tuple(np.concatenate([p[k] for p in self.pieces]) for k in range(4))


def _special_message(otype: int, buf: bytes, pos: int, header_size: int, obj_size: int) -> Any:
    """The ``can.Message`` python-can's BLFReader makes of an error or CAN FD object at ``pos``."""
    from can import Message
    from can.util import dlc2len

    if otype == T_CAN_ERROR_EXT:
        m = CAN_ERROR_EXT.unpack_from(buf, pos)
        return Message(is_error_frame=True, is_extended_id=bool(m[7] & CAN_MSG_EXT),
                       arbitration_id=m[7] & 0x1FFFFFFF, dlc=m[5], data=m[9][: m[5]], channel=m[0] - 1)
    if otype == T_CAN_FD_MESSAGE:
        channel, flags, dlc, can_id, _, _, fd_flags, valid, data = CAN_FD_MSG.unpack_from(buf, pos)
        return Message(arbitration_id=can_id & 0x1FFFFFFF, is_extended_id=bool(can_id & CAN_MSG_EXT),
                       is_remote_frame=bool(flags & REMOTE_FLAG), is_fd=bool(fd_flags & 0x1),
                       is_rx=not bool(flags & 0x1), bitrate_switch=bool(fd_flags & 0x2),
                       error_state_indicator=bool(fd_flags & 0x4), dlc=dlc2len(dlc), data=data[:valid],
                       channel=channel - 1)
    m = CAN_FD_MSG_64.unpack_from(buf, pos)
    channel, dlc, valid, can_id, fd_flags, direction, ext_off = m[0], m[1], m[2], m[4], m[6], m[12], m[13]
    length = min(valid, (ext_off or obj_size) - header_size - CAN_FD_MSG_64.size)
    start = pos + CAN_FD_MSG_64.size
    data = bytes(buf[start:start + max(length, 0)]).ljust(valid, b"\x00")
    return Message(arbitration_id=can_id & 0x1FFFFFFF, is_extended_id=bool(can_id & CAN_MSG_EXT),
                   is_remote_frame=bool(fd_flags & 0x0010), is_fd=bool(fd_flags & 0x1000),
                   is_rx=not direction, bitrate_switch=bool(fd_flags & 0x2000),
                   error_state_indicator=bool(fd_flags & 0x4000), dlc=dlc2len(dlc), data=data,
                   channel=channel - 1)


def _plausible(buf: bytes, pos: int) -> bool:
    """A base header at ``pos`` that a damaged stream is unlikely to fake: magic, version 1 or 2,
    its header size, and an object size that holds the headers and stays bounded."""
    if pos + BASE.size > len(buf):
        return False
    sig, hsize, hver, osize, _ = BASE.unpack_from(buf, pos)
    return (sig == LOBJ and hver in HEADER_BYTES and hsize == 16 + HEADER_BYTES[hver]
            and hsize <= osize <= MAX_OBJECT)


def _resync(buf: bytes, pos: int) -> int:
    """The next position at or after ``pos`` where a plausible object header starts (or len(buf))."""
    while True:
        j = buf.find(LOBJ, pos)
        if j < 0:
            return len(buf)
        if _plausible(buf, j):
            return j
        pos = j + 1


def _count(dropped: dict[str, int], reason: str, n: int = 1) -> None:
    if n:
        dropped[reason] = dropped.get(reason, 0) + n


def _parse_stream(buf: bytes, out: _Builder, dropped: dict[str, int], resync_first: bool,
                  final: bool) -> tuple[int, int]:
    """Read the objects of a piece of one unbroken stream of container data into ``out``.

    Returns (non-CAN objects seen, where reading stopped). ``resync_first``: the piece follows a
    dropped container, so its first bytes may be the rest of an object that started there.
    ``final``: nothing follows, so an object cut off at the end is counted; otherwise reading
    stops at its start, for the caller to join it to the next container's data.
    """
    n = len(buf)
    other = 0
    pos = 0
    if resync_first:
        pos = _resync(buf, 0)
        if pos:
            _count(dropped, "cut_objects")
            _count(dropped, "garbage_bytes", pos)
    while pos < n:
        j = buf.find(LOBJ, pos, pos + 8)  # python-can: the next object within padding of the last
        if j < 0:
            if pos + 8 > n:  # the end: zero padding, or the start of an object cut off
                if not final:
                    return other, pos
                if any(buf[pos:n]):
                    _count(dropped, "cut_objects")
                return other, n
            j = _resync(buf, pos)
            _count(dropped, "garbage_bytes", j - pos)
            pos = j
            continue
        pos = j
        if pos + BASE.size > n:
            break
        if not _plausible(buf, pos):
            j = _resync(buf, pos + 1)
            _count(dropped, "garbage_bytes", j - pos)
            pos = j
            continue
        _, hsize, hver, osize, otype = BASE.unpack_from(buf, pos)
        if pos + osize > n:
            break
        body = pos + 16 + HEADER_BYTES[hver]
        if otype in CLASSIC and osize >= body - pos + CAN_MSG.size:
            pos = _classic_run(buf, pos, out)
            continue
        if otype in SPECIAL:
            out.message(_special_message(otype, buf, body, hsize, osize))
        else:
            other += 1
        pos += osize
    if pos < n and final:
        _count(dropped, "cut_objects")
        return other, n
    return other, min(pos, n)


HEAD_DTYPE = np.dtype([("a", "<u8"), ("b", "<u8")])
"""A base header as two words: magic, header size and version; object size and type."""


def _classic_run(buf: bytes, pos: int, out: _Builder) -> int:
    """Read classic CAN objects from ``pos`` (one at least): as one structured array while every
    next object sits at the same stride with the same base header, checked in chunks of growing
    size; returns where the walk goes on."""
    n = len(buf)
    hver, osize = BASE.unpack_from(buf, pos)[2:4]
    nxt = buf.find(LOBJ, pos + osize, pos + osize + 8)
    stride = nxt - pos
    if nxt < 0 or stride - osize >= 4 or (n - pos) // stride == 0:  # this object alone
        _, can_flags, dlc, can_id, data = CAN_MSG.unpack_from(buf, pos + 16 + HEADER_BYTES[hver])
        out.classic(can_id, can_flags, dlc, data)
        return pos + osize
    ref = np.frombuffer(buf, dtype=HEAD_DTYPE, count=1, offset=pos)[0]
    good, chunk = 0, 64
    while True:
        at = pos + good * stride
        count = min(chunk, (n - at) // stride)
        if count <= 0:
            break
        heads = np.ndarray((count,), dtype=HEAD_DTYPE, buffer=buf, offset=at, strides=(stride,))
        bad = np.flatnonzero((heads["a"] != ref["a"]) | (heads["b"] != ref["b"]))
        good += int(bad[0]) if bad.size else count
        if bad.size or count < chunk:
            break
        chunk = min(chunk * 4, 1 << 16)
    out.run(np.ndarray((good,), dtype=_classic_dtype(stride, hver), buffer=buf, offset=pos))
    return pos + good * stride


class BlfReader:
    """The CAN frames of a .blf, read in pieces of about ``piece_bytes`` of decompressed data, so a
    long log (an hour at 2 kHz holds about 1 GB of objects) never sits in memory whole.

    ``chunks()`` yields ``BlfFrames`` in file order; once it has run, ``dropped``,
    ``other_objects`` and ``containers`` hold the totals. Raises LogFormatError if the file
    cannot be opened or does not start with a BLF header.
    """

    def __init__(self, path: str | Path, piece_bytes: int | None = None) -> None:
        self.path = Path(path)
        self.piece_bytes = piece_bytes or PIECE_BYTES
        self.dropped: dict[str, int] = {}
        self.other_objects = 0
        self.containers = 0
        try:
            with self.path.open("rb") as fh:
                head = fh.read(FILE_HEADER.size)
        except OSError as err:
            raise LogFormatError(f"{self.path}: cannot open the log ({err.strerror})") from err
        if len(head) < FILE_HEADER.size or head[:4] != b"LOGG":
            raise LogFormatError(f"{self.path}: not a BLF file (no 'LOGG' header)")
        self.header_size = FILE_HEADER.unpack(head)[1]

    def _containers(self, raw: Any) -> Iterator[bytes | None]:
        """Each container's data in file order; None for one that is dropped (and counted)."""
        n = len(raw)
        pos = self.header_size
        while pos < n:
            if pos + BASE.size > n or raw[pos:pos + 4] != LOBJ:
                j = raw.find(LOBJ, pos + 1)
                j = n if j < 0 else j
                if any(raw[pos:j]):  # zero padding is not garbage
                    _count(self.dropped, "garbage_bytes", j - pos)
                pos = j
                continue
            _, _, _, osize, otype = BASE.unpack_from(raw, pos)
            if osize < BASE.size:
                _count(self.dropped, "garbage_bytes", 4)
                pos += 4
                continue
            end = pos + osize
            if otype != T_LOG_CONTAINER:
                pos = end + osize % 4
                continue
            self.containers += 1
            if end > n or osize < BASE.size + CONTAINER.size:
                _count(self.dropped, "truncated_containers")
                yield None
                return
            method, size = CONTAINER.unpack_from(raw, pos + BASE.size)
            cdata = raw[pos + BASE.size + CONTAINER.size:end]
            pos = end + osize % 4
            if method == 0:
                yield bytes(cdata)
                continue
            if method != 2:
                _count(self.dropped, "unknown_compression_containers")
                yield None
                continue
            z = zlib.decompressobj()
            try:
                data = z.decompress(cdata)
            except zlib.error:
                data = None
            if data is None or not z.eof or (size and len(data) != size):
                _count(self.dropped, "corrupt_containers")
                yield None
                continue
            yield data

    def chunks(self) -> Iterator[BlfFrames]:
        """The frames, a piece at a time (each piece's ``special`` indexed within the piece)."""
        import mmap

        with self.path.open("rb") as fh:
            size = self.path.stat().st_size
            raw: Any = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
            try:
                yield from self._pieces(raw)
            finally:
                if isinstance(raw, mmap.mmap):
                    raw.close()

    def _pieces(self, raw: Any) -> Iterator[BlfFrames]:
        parts: list[bytes] = []
        held, resync = 0, False
        for data in self._containers(raw):
            if data is None:  # the stream breaks: what is held ends here
                if parts:
                    yield self._piece(b"".join(parts), resync, final=True)[0]
                parts, held, resync = [], 0, True
                continue
            parts.append(data)
            held += len(data)
            if held >= self.piece_bytes:
                buf = b"".join(parts)
                frames, stop = self._piece(buf, resync, final=False)
                yield frames
                parts, held, resync = [buf[stop:]], len(buf) - stop, False
        if parts:
            yield self._piece(b"".join(parts), resync, final=True)[0]

    def _piece(self, buf: bytes, resync: bool, final: bool) -> tuple[BlfFrames, int]:
        out = _Builder()
        other, stop = _parse_stream(buf, out, self.dropped, resync, final)
        self.other_objects += other
        arb_id, flags, length, payload = out.result()
        return BlfFrames(arb_id, flags, length, payload, out.special), stop


def read_blf_frames(path: str | Path) -> BlfFrames:
    """Every CAN frame of a .blf file, in file order, in one piece (see ``BlfReader``)."""
    reader = BlfReader(path)
    pieces = list(reader.chunks())
    special: dict[int, Any] = {}
    base = 0
    for f in pieces:
        special.update({base + i: m for i, m in f.special.items()})
        base += len(f)
    kinds = (("arb_id", np.uint32), ("flags", np.uint8), ("length", np.int16), ("payload", np.uint64))
    cols = [np.concatenate([getattr(f, c) for f in pieces]) if pieces else np.zeros(0, dtype=d)
            for c, d in kinds]
    return BlfFrames(*cols, special, dict(reader.dropped), reader.other_objects, reader.containers)
