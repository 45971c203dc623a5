"""Serial framing: round trips, CRC, range checks, gpsd-style garbage table, counters, bounded buffer."""

from __future__ import annotations

import binascii
import random
from dataclasses import replace

import pytest

from gyrocal.errors import ProtocolError
from gyrocal.protocol import termsets
from gyrocal.protocol.messages import (
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffWrite,
    Hello,
    NakReason,
    Sample,
    coeff_set_bytes,
    coeff_set_crc,
)
from gyrocal.protocol.serial_framing import (
    MAX_FRAME,
    SAMPLE_FRAME_SIZE,
    SYNC,
    FrameDecoder,
    encode_frame,
)

SEED000 = termsets.SEED000_ID


def q_sample(seq: int, rng: random.Random | None = None) -> Sample:
    """A sample whose values are exact wire counts, so a round trip must return it unchanged."""
    r = rng or random.Random(seq)
    return Sample(seq, seq * 500 / 1e6,
                  tuple(r.randint(-2**31, 2**31 - 1) / 1e6 for _ in range(3)),  # type: ignore[arg-type]
                  tuple(r.randint(-32768, 32767) / 1e4 for _ in range(3)),  # type: ignore[arg-type]
                  r.randint(-32768, 32767) / 100)


def coeffs(p: int, scale: float = 1e-3, seed: int = 0) -> list[list[float]]:
    r = random.Random(seed)
    return [[r.uniform(-scale, scale) for _ in range(p)] for _ in range(3)]


ALL_MESSAGES = [
    q_sample(0), q_sample(123456),
    Sample(0xFFFFFFFF, 3600.0, (2147.483647, -2147.483648, 1e-6), (3.2767, -3.2768, 1.0), -327.68),
    Hello(0xDEADBEEF, "1.2.3", 17, 2000), Hello(0, "0.0.0", 0),
    CoeffWrite(1, SEED000, coeffs(10)), CoeffWrite(0xFFFFFFFF, termsets.EXTENDED_TEMP_ID, coeffs(14)),
    CoeffWrite(2, 0, [[], [], []]), CoeffWrite(3, 7, coeffs(21)),
    CoeffAck(1, 0x12345678), CoeffNak(2, 0xFFFFFFFF, NakReason.UNKNOWN_TERMS), CoeffNak(2, 0, 200),
    CoeffRead(), CoeffReport(9, SEED000, coeffs(10, seed=3)),
]


@pytest.mark.parametrize("msg", ALL_MESSAGES, ids=lambda m: type(m).__name__)
def test_every_message_round_trips_exactly_through_one_frame(msg: object) -> None:
    dec = FrameDecoder()
    assert dec.feed(encode_frame(msg)) == [msg]
    assert dec.stats.frames == 1 and dec.stats.errors() == 0 and dec.buffered == 0


def test_crc_is_ieee_crc32_over_type_length_payload() -> None:
    assert binascii.crc32(b"123456789") == 0xCBF43926  # the standard check value
    frame = encode_frame(CoeffAck(1, 2))
    assert frame[:2] == SYNC
    assert int.from_bytes(frame[-4:], "little") == binascii.crc32(frame[2:-4])


def test_sample_frame_matches_the_documented_hex_dump() -> None:
    s = Sample(7, 1.5, (0.001, -2.5, 100.0), (0.0, 0.5, -1.0), 23.45)
    expected = ("a5 5a 02 20 00 07 00 00 00 60 e3 16 00 00 00 00 00 e8 03 00 00 60 da d9 ff 00 e1 f5 05"
                " 00 00 88 13 f0 d8 29 09 d2 be 8c 27")
    assert encode_frame(s).hex(" ") == expected
    assert len(encode_frame(s)) == SAMPLE_FRAME_SIZE == 41


def test_coeff_set_crc_is_crc32_of_the_write_payload() -> None:
    c = coeffs(10)
    frame = encode_frame(CoeffWrite(5, SEED000, c))
    assert frame[5:-4] == coeff_set_bytes(5, SEED000, c)
    assert coeff_set_crc(5, SEED000, c) == binascii.crc32(frame[5:-4])
    assert coeff_set_crc(5, SEED000, c) != coeff_set_crc(6, SEED000, c)


@pytest.mark.parametrize("msg", [
    Sample(-1, 0.0, (0, 0, 0), (0, 0, 0), 0),
    Sample(0, -1.0, (0, 0, 0), (0, 0, 0), 0),
    Sample(0, 0.0, (2147.5, 0, 0), (0, 0, 0), 0),
    Sample(0, 0.0, (0, 0, float("nan")), (0, 0, 0), 0),
    Sample(0, 0.0, (0, 0, 0), (0, 3.3, 0), 0),
    Sample(0, 0.0, (0, 0, 0), (0, 0, 0), 400.0),
    Hello(0, "1.2", 0), Hello(0, "1.2.256", 0), Hello(2**32, "1.2.3", 0), Hello(1, "1.2.3", 1, 70000),
    CoeffWrite(1, SEED000, coeffs(22)), CoeffWrite(1, 2**16, coeffs(3)), CoeffWrite(-1, 0, coeffs(3)),
    CoeffWrite(1, 0, [[1.0], [2.0]]), CoeffWrite(1, 0, [[1.0], [2.0], [3.0, 4.0]]),
    CoeffWrite(1, 0, [[float("inf")], [0.0], [0.0]]), CoeffNak(1, 2, 256), CoeffAck(1, -1),
], ids=repr)
def test_out_of_range_fields_raise_protocol_error(msg: object) -> None:
    with pytest.raises(ProtocolError):
        encode_frame(msg)


def test_unknown_message_object_raises_protocol_error() -> None:
    with pytest.raises(ProtocolError):
        encode_frame(object())


FRAME = encode_frame(q_sample(1))
NEXT = encode_frame(q_sample(2))
GARBAGE_TABLE = [
    ("nothing", b""),
    ("one byte", b"\x00"),
    ("half sync", b"\xa5"),
    ("sync only", SYNC),
    ("sync twice", SYNC + SYNC),
    ("header of a sample, truncated", FRAME[:12]),
    ("whole frame minus its last byte", FRAME[:-1]),
    ("oversize length", SYNC + b"\x02\xff\xff"),
    ("wrong length for SAMPLE", SYNC + b"\x02\x10\x00" + bytes(20)),
    ("unknown type, long length", SYNC + b"\x7f\x00\x02" + bytes(10)),
    ("frame with a flipped payload bit", FRAME[:20] + bytes([FRAME[20] ^ 1]) + FRAME[21:]),
    ("random noise", bytes(random.Random(7).randrange(256) for _ in range(300))),
    ("noise full of sync words", (SYNC + b"\x02\x20\x00\x99") * 20),
]


@pytest.mark.parametrize("name,garbage", GARBAGE_TABLE, ids=[g[0] for g in GARBAGE_TABLE])
@pytest.mark.parametrize("chunk", [1, 7, 4096])
def test_garbage_before_a_frame_is_skipped_and_the_frame_found(name: str, garbage: bytes, chunk: int) -> None:
    stream = garbage + NEXT + encode_frame(q_sample(3))
    dec = FrameDecoder()
    out = [m for i in range(0, len(stream), chunk) for m in dec.feed(stream[i : i + chunk])]
    assert out == [q_sample(2), q_sample(3)]
    # Every byte that is not part of a yielded frame is counted as garbage exactly once.
    assert dec.stats.garbage_bytes == len(garbage)
    assert dec.stats.bytes == len(stream)


def test_oversize_length_is_counted_and_resynced() -> None:
    dec = FrameDecoder()
    out = dec.feed(SYNC + b"\x02\x01\x02" + FRAME)
    assert out == [q_sample(1)] and dec.stats.oversize == 1 and dec.stats.resyncs == 1


def test_length_that_does_not_fit_the_type_is_counted() -> None:
    dec = FrameDecoder()
    bad = SYNC + b"\x11\x04\x00" + b"abcd"
    bad += binascii.crc32(bad[2:]).to_bytes(4, "little")  # a valid CRC, but ACK needs 8 bytes
    assert dec.feed(bad + FRAME) == [q_sample(1)]
    assert dec.stats.length_errors == 1


def test_coeff_payload_whose_n_terms_disagrees_with_length_is_rejected() -> None:
    good = encode_frame(CoeffWrite(1, SEED000, coeffs(10)))
    body = bytearray(good[2:-4])
    body[3 + 6] = 9  # n_terms byte, the payload still holds 10 terms
    bad = SYNC + bytes(body) + binascii.crc32(bytes(body)).to_bytes(4, "little")
    dec = FrameDecoder()
    assert dec.feed(bad) == [] and dec.stats.length_errors == 1


def test_unknown_type_is_rejected_on_its_header_and_counted() -> None:
    body = b"\x7e\x03\x00xyz"
    frame = SYNC + body + binascii.crc32(body).to_bytes(4, "little")
    dec = FrameDecoder()
    assert dec.feed(frame + FRAME) == [q_sample(1)]
    assert dec.stats.unknown_types == 1 and dec.stats.garbage_bytes == len(frame)


def test_seq_gap_is_counted_and_u32_wrap_is_not_a_gap() -> None:
    dec = FrameDecoder()
    seqs = [0xFFFFFFFE, 0xFFFFFFFF, 0, 1, 5, 6]
    dec.feed(b"".join(encode_frame(q_sample(s)) for s in seqs))
    assert dec.stats.seq_gaps == 1 and dec.stats.lost_samples == 3


def test_hello_restarts_seq_so_a_new_session_is_not_a_gap() -> None:
    dec = FrameDecoder()
    stream = [q_sample(100), q_sample(101), Hello(1, "1.0.0", 2), q_sample(0), q_sample(1)]
    dec.feed(b"".join(encode_frame(m) for m in stream))
    assert dec.stats.seq_gaps == 0 and dec.stats.frames == 5


def test_a_sample_sent_twice_is_taken_once_and_counted() -> None:
    """A copy of the previous sample (same seq) is dropped and counted in ``repeated``, or in
    ``conflicting`` when its values differ: believed, a copy weighs its sample twice and a forged one
    is learnt (rc36b H2, on CAN)."""
    dec = FrameDecoder()
    forged = replace(q_sample(1), gyro_dps=(0.5, 0.0, 0.0))
    out = dec.feed(b"".join(encode_frame(m) for m in [q_sample(0), q_sample(1), q_sample(1), forged,
                                                        q_sample(2)]))
    assert [m.seq for m in out] == [0, 1, 2] and out[1] == q_sample(1)
    assert dec.stats.repeated == 1 and dec.stats.conflicting == 1 and dec.stats.seq_gaps == 0
    assert dec.stats.frames == 3


def test_buffer_stays_bounded_under_endless_noise() -> None:
    rng = random.Random(1)
    dec = FrameDecoder()
    for _ in range(200):
        dec.feed(bytes(rng.randrange(256) for _ in range(1000)) + SYNC + b"\x7f\x00\x02")
        assert dec.buffered <= MAX_FRAME
    assert dec.feed(b"\x00" * MAX_FRAME + FRAME) == [q_sample(1)]


def test_byte_at_a_time_feed_equals_bulk_feed() -> None:
    stream = b"".join(encode_frame(m) for m in ALL_MESSAGES)
    one = FrameDecoder()
    out = [m for b in stream for m in one.feed(bytes([b]))]
    assert out == ALL_MESSAGES == FrameDecoder().feed(stream)


def test_numpy_scalars_and_arrays_encode_like_python_numbers() -> None:
    np = pytest.importorskip("numpy")
    gyro, accel = np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.0, 1.0])
    s = Sample(np.int64(5), np.float64(0.5), gyro, accel, np.float64(25))
    assert FrameDecoder().feed(encode_frame(s)) == [Sample(5, 0.5, (0.1, 0.2, 0.3), (0.0, 0.0, 1.0), 25.0)]
    c = np.arange(30.0).reshape(3, 10) * 1e-4
    assert coeff_set_crc(np.int64(2), SEED000, c) == coeff_set_crc(2, SEED000, c.tolist())
    assert CoeffWrite(2, SEED000, c) == CoeffWrite(2, SEED000, c.tolist())
