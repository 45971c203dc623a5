"""The fast .blf path (readers.blf + readers.canbulk) against python-can's BLFReader and our
CanDecoder frame by frame: the same frames, the same samples bit for bit, the same counters; and
what a damaged file loses is counted, never believed."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import can
import numpy as np
import pytest
from can.io import blf as pcblf

from gyrocal.protocol.can_codec import CanCodec
from gyrocal.protocol.messages import CoeffRead, CoeffReport, Hello, HelloRequest, Sample
from gyrocal.readers import ReadOptions, read_any
from gyrocal.readers.blf import FLAG_EXT, FLAG_REMOTE, read_blf_frames
from gyrocal.readers.canlog import CanRecording, read_canlog

DATA = Path(__file__).resolve().parent.parent / "data"


def _same_log(path: Path, ignore_blf: bool = False) -> tuple:
    """Fast and reference reads of ``path``; asserts equal columns (bit for bit), counters, metadata."""
    fast = read_canlog(str(path), ReadOptions(), fast=True)
    ref = read_canlog(str(path), ReadOptions(), fast=False)
    assert list(fast.columns) == list(ref.columns)
    for k in ref.columns:
        assert fast[k].dtype == ref[k].dtype == np.float64
        np.testing.assert_array_equal(fast[k].view(np.uint64), ref[k].view(np.uint64), err_msg=k)
    fd = {k: v for k, v in fast.dropped.items() if not (ignore_blf and k.startswith("blf_"))}
    assert fd == ref.dropped
    assert fast.metadata == ref.metadata and fast.data_rows == ref.data_rows
    return fast, ref


def _same_frames(path: Path) -> None:
    """readers.blf gives python-can's BLFReader frames: id, flags, data."""
    frames = read_blf_frames(path)
    ref = list(can.BLFReader(str(path)))
    assert len(frames) == len(ref)
    for i, m in enumerate(ref):
        if i in frames.special:
            got = frames.special[i]
            fields = ("arbitration_id", "is_extended_id", "is_error_frame", "is_fd", "data")
            assert [getattr(got, f) for f in fields] == [getattr(m, f) for f in fields], i
            continue
        assert not m.is_error_frame and not m.is_fd, i
        fl = int(frames.flags[i])
        assert int(frames.arb_id[i]) == m.arbitration_id, i
        assert bool(fl & FLAG_EXT) == m.is_extended_id and bool(fl & FLAG_REMOTE) == m.is_remote_frame, i
        n = int(frames.length[i])
        assert int(frames.payload[i]).to_bytes(8, "little")[:n] == bytes(m.data), i


def _samples(rng: np.random.Generator, n: int, seq0: int, t0: float, rate: float = 2000.0) -> list[Sample]:
    g = rng.uniform(-300, 300, (n, 3))
    a = rng.uniform(-2, 2, (n, 3))
    temp = rng.uniform(-20, 60, n)
    return [Sample(seq0 + i, t0 + i / rate, tuple(g[i]), tuple(a[i]), float(temp[i])) for i in range(n)]


def _unit_frames(rng: np.random.Generator) -> list[can.Message]:
    """Two switch-ons of a unit: HELLO, a coefficient report, samples over a u16 seq wrap."""
    codec = CanCodec()
    frames: list[can.Message] = []
    for boot, seq0, n in ((1, 65000, 1500), (2, 0, 900)):
        frames += codec.encode(Hello(4242, "1.2.3", boot, 2000))
        frames += codec.encode(CoeffReport(5, 0x0001, ([0.01], [-0.02], [0.005])))
        for s in _samples(rng, n, seq0, 100.0 * boot):
            frames += codec.encode(s)
    return frames


def _write(path: Path, frames: list[can.Message], container: int = 4000) -> None:
    with can.BLFWriter(str(path), max_container_size=container) as out:
        for i, f in enumerate(frames):
            f.timestamp = 1.7e9 + i * 1e-4
            out.on_message_received(f)


def test_shipped_recording_reads_the_same_fast() -> None:
    path = DATA / "sim_can" / "virtual_unit.blf"
    _same_frames(path)
    fast, _ = _same_log(path)
    assert len(fast) == 4000 and not fast.dropped
    rec = CanRecording(str(path))
    list(rec.messages())
    assert rec.bulk_samples >= 3990  # all but the first sample after each anchor-less start


@pytest.mark.parametrize("piece", [None, 3001])  # whole, or parsed a few containers at a time
def test_mixed_bus_with_damage_of_every_kind(piece: int | None, tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    from gyrocal.readers import blf

    if piece:
        monkeypatch.setattr(blf, "PIECE_BYTES", piece)
    rng = np.random.default_rng(11)
    frames = _unit_frames(rng)
    codec = CanCodec()
    out: list[can.Message] = []
    for i, f in enumerate(frames):
        r = rng.random()
        if r < 0.004:  # a lost frame
            continue
        out.append(f)
        if r > 0.997:  # the same frame twice
            out.append(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=False))
        elif 0.99 < r <= 0.991:  # a short frame with the unit's id
            out.append(can.Message(arbitration_id=f.arbitration_id, data=f.data[:5], is_extended_id=False))
        elif 0.991 < r <= 0.992:  # remote and extended frames with the unit's ids
            out.append(can.Message(arbitration_id=f.arbitration_id, is_remote_frame=True, dlc=8,
                                   is_extended_id=False))
            out.append(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True))
        elif 0.992 < r <= 0.993:  # an error frame, a CAN FD copy of the frame, a 64-byte FD frame
            out.append(can.Message(is_error_frame=True, arbitration_id=0x1D0, data=b"\x01\x02"))
            out.append(can.Message(arbitration_id=0x7A5, is_fd=True, data=bytes(range(48))))
        elif 0.993 < r <= 0.994:
            out.append(can.Message(arbitration_id=f.arbitration_id, is_fd=True, data=f.data,
                                   is_extended_id=False))
            out.pop(-2)  # the classic original goes: the unit sent it as an FD frame
        if i % 97 == 0:  # other nodes and other protocols on the bus
            data = rng.integers(0, 256, int(rng.integers(0, 9)), dtype=np.uint8).tobytes()
            fid = int(rng.integers(0, 0x800))
            out.append(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
            out.append(can.Message(arbitration_id=0x18FEF100, data=b"\x00" * 8, is_extended_id=True))
        if i % 1301 == 0:  # the host asks
            for m in (HelloRequest(), CoeffRead()):
                out += codec.encode(m)
        if i == 2500:  # an anchor that disagrees with its sample
            t = codec.encode(Sample(65000 + 900, 0.0, (0, 0, 0), (0, 0, 0), 0.0))[0]
            out.append(t)
    # out-of-order frames: swap a few neighbours
    for j in rng.integers(10, len(out) - 10, 6):
        out[j], out[j + 1] = out[j + 1], out[j]
    path = tmp_path / "mixed.blf"
    _write(path, out)
    _same_frames(path)
    fast, ref = _same_log(path)
    assert len(fast) > 2300 and set(fast["session"]) == {0.0, 1.0}
    assert ref.dropped.get("incomplete", 0) > 5 and ref.dropped.get("length_errors", 0) > 0
    # remote and extended frames on the unit's ids are foreign (protocol.md's table), not unknown types
    assert ref.dropped.get("error_frames", 0) > 0 and not ref.dropped.get("unknown_types", 0)
    assert int(ref.metadata["foreign_frames"]) > 0
    assert fast.metadata["foreign_frames"] == ref.metadata["foreign_frames"]
    assert int(ref.metadata["host_frames"]) >= 4
    rec = CanRecording(str(path))
    list(rec.messages())
    assert rec.bulk_samples > 0.8 * len(fast)  # the bulk path did most of it


def test_clean_log_over_a_long_gap_and_a_time_jump(tmp_path: Path) -> None:
    """Regular triples, but the time steps by 0.4 s without an anchor and the seq jumps: the bulk
    decoder must hand exactly those samples to the frame-by-frame decoder."""
    rng = np.random.default_rng(5)
    codec = CanCodec()
    frames = codec.encode(Hello(1, "1.0.0", 1, 2000))
    s1 = _samples(rng, 700, 10, 5.0)
    s2 = _samples(rng, 300, 710, 5.0 + 700 / 2000 + 0.6)  # 0.6 s late, no anchor: > 2**19 us off
    s3 = _samples(rng, 300, 1200, 6.0)  # a gap of 190 samples
    for s in s1 + s2 + s3:
        frames += codec.encode(s)
    path = tmp_path / "gap.blf"
    _write(path, frames, container=128 * 1024)
    fast, ref = _same_log(path)
    # the 0.6 s jump without an anchor cannot be placed in time (the 20-bit time wraps at 1.05 s): those
    # samples are dropped as implausible until an anchor gives the time again, by both decoders
    assert len(fast) == len(ref) > 1000 and ref.dropped.get("implausible", 0) > 0


def _handmade_blf(path: Path, objects: list[bytes], compress: list[bool]) -> None:
    """A BLF with the given inner objects split over len(compress) containers (v1 file header)."""
    body = b"".join(objects)
    cuts = np.linspace(0, len(body), len(compress) + 1).astype(int)
    out = []
    for k, z in enumerate(compress):
        part = body[cuts[k]:cuts[k + 1]]
        data = zlib.compress(part) if z else part
        size = pcblf.OBJ_HEADER_BASE_STRUCT.size + pcblf.LOG_CONTAINER_STRUCT.size + len(data)
        out.append(pcblf.OBJ_HEADER_BASE_STRUCT.pack(b"LOBJ", 16, 1, size, pcblf.LOG_CONTAINER)
                   + pcblf.LOG_CONTAINER_STRUCT.pack(2 if z else 0, len(part)) + data + b"\x00" * (size % 4))
    head = pcblf.FILE_HEADER_STRUCT.pack(b"LOGG", 144, 5, 0, 0, 0, 2, 6, 8, 1, 0, 0, 0, 0,
                                         *([0] * 8), *([0] * 8))
    path.write_bytes(head + b"\x00" * (144 - len(head)) + b"".join(out))


def _object(otype: int, payload: bytes, version: int) -> bytes:
    header = (struct.pack("<LHHQ", 2, 0, 0, 12345) if version == 1
              else struct.pack("<LBxHQ8x", 2, 0, 0, 12345))
    size = 16 + len(header) + len(payload)
    return pcblf.OBJ_HEADER_BASE_STRUCT.pack(b"LOBJ", 16 + len(header), version, size, otype) + header + \
        payload + b"\x00" * (size % 4)


def test_v2_headers_can_message2_and_uncompressed_containers(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    codec = CanCodec()
    frames = codec.encode(Hello(9, "2.0.0", 4, 2000))
    for s in _samples(rng, 600, 0, 1.0):
        frames += codec.encode(s)
    objs = []
    for i, f in enumerate(frames):
        data = bytes(f.data).ljust(8, b"\0")
        can_msg = pcblf.CAN_MSG_STRUCT.pack(1, 0, len(f.data), f.arbitration_id, data)
        if i < 700:  # CAN_MESSAGE2 (frame length, bit count, 3 reserved bytes) with header v2
            objs.append(_object(pcblf.CAN_MESSAGE2, can_msg + struct.pack("<LB3x", 111, 130), 2))
        else:
            objs.append(_object(pcblf.CAN_MESSAGE, can_msg, 1 + (i // 300) % 2))
        if i % 250 == 0:  # a global marker: not a frame, not dropped data
            objs.append(_object(pcblf.GLOBAL_MARKER, pcblf.GLOBAL_MARKER_STRUCT.pack(0, 0, 0, 0, 1, 1, 1)
                                + b"abc", 1))
    path = tmp_path / "v2.blf"
    _handmade_blf(path, objs, [True, False, True, True, False])
    _same_frames(path)
    fast, _ = _same_log(path)
    assert len(fast) == 600 and not fast.dropped
    assert read_blf_frames(path).other_objects == len(range(0, len(frames), 250))


def _container_spans(path: Path) -> list[tuple[int, int, int]]:
    """(file offset, file end, uncompressed bytes) of each top-level container."""
    raw = path.read_bytes()
    pos, out = 144, []
    while pos < len(raw):
        _, _, _, size, _ = pcblf.OBJ_HEADER_BASE_STRUCT.unpack_from(raw, pos)
        _, usize = pcblf.LOG_CONTAINER_STRUCT.unpack_from(raw, pos + 16)
        out.append((pos, pos + size, usize))
        pos += size + size % 4
    return out


@pytest.mark.parametrize("container", [4800, 4000])  # objects whole in each container, or spanning two
@pytest.mark.parametrize("damage", ["corrupt", "truncated"])
@pytest.mark.parametrize("piece", [None, 9000])
def test_a_damaged_container_is_counted_and_never_believed(container: int, damage: str, piece: int | None,
                                                           tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    from gyrocal.readers import blf

    if piece:
        monkeypatch.setattr(blf, "PIECE_BYTES", piece)
    rng = np.random.default_rng(container)
    frames = _unit_frames(rng)  # classic frames only: 48 bytes per object
    path = tmp_path / "whole.blf"
    _write(path, frames, container)
    spans = _container_spans(path)
    k = len(spans) // 2 if damage == "corrupt" else len(spans) - 1
    raw = bytearray(path.read_bytes())
    start, end, _ = spans[k]
    if damage == "corrupt":
        mid = (start + 32 + end) // 2
        raw[mid:mid + 6] = bytes(b ^ 0x5A for b in raw[mid:mid + 6])
    else:
        raw = raw[: (start + end) // 2]
    bad = tmp_path / f"{damage}.blf"
    bad.write_bytes(bytes(raw))
    # what the damaged container held: every frame with a byte in it is lost, whole
    lo, hi = sum(s[2] for s in spans[:k]), sum(s[2] for s in spans[: k + 1])
    keep = [f for j, f in enumerate(frames) if 48 * (j + 1) <= lo or 48 * j >= hi]
    expect = tmp_path / "expect.blf"
    _write(expect, keep, 128 * 1024)
    fast = read_canlog(str(bad), ReadOptions(), fast=True)
    ref = read_canlog(str(expect), ReadOptions(), fast=False)
    for c in ref.columns:
        np.testing.assert_array_equal(fast[c].view(np.uint64), ref[c].view(np.uint64), err_msg=c)
    assert {k: v for k, v in fast.dropped.items() if not k.startswith("blf_")} == ref.dropped
    reason = "blf_corrupt_containers" if damage == "corrupt" else "blf_truncated_containers"
    assert fast.dropped[reason] == 1
    spanning = container % 48 != 0
    assert fast.dropped.get("blf_cut_objects", 0) == (0 if not spanning else 1 + (damage == "corrupt"))
    assert len(ref) < len(read_canlog(str(path), ReadOptions(), fast=False))
    # the reader registry and fit say so
    assert read_any(bad).dropped[reason] == 1


def test_not_a_blf_goes_to_python_can_which_names_the_fault(tmp_path: Path) -> None:
    from gyrocal.errors import LogFormatError

    path = tmp_path / "x.blf"
    path.write_bytes(b"NOTABLF" * 100)
    with pytest.raises(LogFormatError, match="python-can"):
        read_any(path)


def test_replay_of_a_blf_decides_the_same_fast_or_frame_by_frame(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """`gyrocal replay` takes the bulk blocks: the same samples, sessions and decisions."""
    import time

    from gyrocal.daemon.config import load_config
    from gyrocal.readers import canlog
    from gyrocal.replay.run import replay
    from gyrocal.replay.source import open_recording

    def cfg():  # noqa: ANN202
        state = tmp_path / f"state-{time.monotonic_ns()}"
        state.mkdir()
        return load_config(None, {"state_dir": str(state), "control_socket": str(tmp_path / "c.sock"),
                                  "watchdog": False})

    path = str(DATA / "sim_can" / "virtual_unit.blf")
    fast = replay(open_recording(path), cfg())
    monkeypatch.setattr(canlog, "CanRecording",
                        lambda p, dbc=None, fast=True, node_id=0, _cls=canlog.CanRecording:
                        _cls(p, dbc, False, node_id))
    slow = replay(open_recording(path), cfg())
    for r in (fast, slow):
        r.pop("wall_s"), r.pop("samples_per_s")  # the host's speed
    assert fast["samples"] == slow["samples"] == 4000
    assert json.dumps(fast, sort_keys=True, default=str) == json.dumps(slow, sort_keys=True, default=str)


def test_random_damage_never_invents_samples(tmp_path: Path) -> None:
    """Bytes flipped anywhere in a recording (headers, compressed data): the fast path either reads
    a subset of the true samples, counting what it dropped, or says the file is not a BLF."""
    from gyrocal.errors import LogFormatError

    src = DATA / "sim_can" / "virtual_unit.blf"
    truth = read_canlog(str(src), ReadOptions(), fast=False)
    rows = {tuple(r) for r in np.column_stack([truth[c] for c in ("t", "wx", "wy", "wz", "ax", "temp")])}
    raw = src.read_bytes()
    rng = np.random.default_rng(21)
    for trial in range(12):
        bad = bytearray(raw)
        for pos in rng.integers(0, len(raw), 1 + trial % 4):
            bad[pos] ^= int(rng.integers(1, 256))
        path = tmp_path / f"damaged{trial}.blf"
        path.write_bytes(bytes(bad))
        try:
            log = read_canlog(str(path), ReadOptions(), fast=True)
        except LogFormatError:
            continue
        got = np.column_stack([log[c] for c in ("t", "wx", "wy", "wz", "ax", "temp")])
        assert all(tuple(r) in rows for r in got), trial
        assert len(log) == len(truth) or log.dropped, trial


def test_a_dbc_whose_scales_the_decoder_does_not_apply_is_not_decoded_in_bulk(tmp_path: Path) -> None:
    """CanDecoder divides by its own counts per unit; a DBC saying otherwise must not make the bulk
    path disagree with it: the bulk path stands aside (sample_signals is None)."""
    from gyrocal.protocol.can_codec import DEFAULT_DBC
    from gyrocal.readers.canbulk import sample_signals

    text = DEFAULT_DBC.read_text()
    dbc = tmp_path / "other.dbc"
    dbc.write_text(text.replace('GYRO_X : 16|32@1- (1e-06,0)', 'GYRO_X : 16|32@1- (1e-05,0)'))
    assert sample_signals(CanCodec(dbc)) is None and sample_signals(CanCodec()) is not None
    path = DATA / "sim_can" / "virtual_unit.blf"
    fast = read_canlog(str(path), ReadOptions(dbc=str(dbc)), fast=True)
    ref = read_canlog(str(path), ReadOptions(dbc=str(dbc)), fast=False)
    for c in ref.columns:
        np.testing.assert_array_equal(fast[c], ref[c])
    assert len(fast) == 4000
