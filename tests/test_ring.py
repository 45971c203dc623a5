"""Ring buffer: FIFO order, wrap-around, overflow keeps the newest and counts the lost, SPSC threads."""

import threading
from dataclasses import dataclass

import numpy as np
import pytest

from gyrocal.daemon.ring import SAMPLE_DTYPE, RingBuffer


@dataclass(frozen=True)
class _S:  # the fields of protocol.messages.Sample that the ring reads
    seq: int
    t_s: float
    gyro_dps: tuple[float, float, float]
    accel_g: tuple[float, float, float]
    temp_c: float


def _sample(i: int) -> _S:
    return _S(i, i / 100.0, (i + 0.1, i + 0.2, i + 0.3), (0.0, 0.0, 1.0), 25.0 + i)


def _fill(ring: RingBuffer, start: int, stop: int) -> None:
    for i in range(start, stop):
        ring.push(_sample(i), rx_time=1000.0 + i)


def test_ring_pop_returns_fields_in_fifo_order_with_units() -> None:
    ring = RingBuffer(8)
    _fill(ring, 0, 5)
    out = ring.pop()
    assert out.dtype == SAMPLE_DTYPE and len(out) == 5
    assert out["seq"].tolist() == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(out["wy"], np.arange(5) + 0.2)
    np.testing.assert_allclose(out["temp"], 25.0 + np.arange(5))
    np.testing.assert_allclose(out["rx"], 1000.0 + np.arange(5))
    assert ring.pop().size == 0 and ring.popped == 5 and ring.lost == 0


def test_ring_wraps_around_many_times_without_loss_when_drained() -> None:
    ring = RingBuffer(7)
    got = []
    for k in range(50):  # pushes of 5 into capacity 7: every pop crosses the end sooner or later
        _fill(ring, 5 * k, 5 * k + 5)
        got.extend(ring.pop(max_n=3).tolist())
        got.extend(ring.pop().tolist())
    assert [r[0] for r in got] == list(range(250))
    assert ring.pushed == 250 and ring.popped == 250 and ring.lost == 0 and len(ring) == 0


def test_ring_overflow_keeps_newest_and_counts_lost() -> None:
    ring = RingBuffer(10)
    _fill(ring, 0, 25)
    assert len(ring) == 10 and ring.lost == 15  # known before the consumer looks
    out = ring.pop()
    assert out["seq"].tolist() == list(range(15, 25))
    assert ring.lost == 15 and ring.popped == 10 and ring.pushed == 25


def test_ring_pop_max_n_then_overflow_counts_only_unread() -> None:
    ring = RingBuffer(4)
    _fill(ring, 0, 4)
    assert ring.pop(max_n=2)["seq"].tolist() == [0, 1]
    _fill(ring, 4, 10)  # 2..9 unread, capacity 4: 2..5 lost
    assert ring.pop()["seq"].tolist() == [6, 7, 8, 9]
    assert ring.lost == 4 and ring.pushed == ring.popped + ring.lost


def test_ring_memory_is_preallocated_and_constant() -> None:
    ring = RingBuffer(16)
    buf = ring._buf
    _fill(ring, 0, 10_000)
    ring.pop()
    assert ring._buf is buf and ring._buf.nbytes == 16 * SAMPLE_DTYPE.itemsize


def test_ring_rejects_zero_capacity() -> None:
    with pytest.raises(ValueError, match="capacity"):
        RingBuffer(0)


def test_ring_spsc_threads_deliver_in_order_and_account_for_every_sample() -> None:
    """A producer thread outpaces a consumer thread on a small ring: what arrives is in order, never
    torn (all fields of a record agree), and pushed == popped + lost + unread."""
    ring, n = RingBuffer(64), 60_000
    got: list[np.ndarray] = []
    done = threading.Event()

    def produce() -> None:
        for i in range(n):
            ring.push_values(i, i * 1e-3, i, i, i, i, i, i, i, float(i))
        done.set()

    def consume() -> None:
        while not done.is_set() or len(ring):
            got.append(ring.pop(max_n=50))

    threads = [threading.Thread(target=produce), threading.Thread(target=consume)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    out = np.concatenate(got)
    seq = out["seq"].astype(np.int64)
    assert np.all(np.diff(seq) > 0)
    for f in ("wx", "ay", "temp", "rx"):
        np.testing.assert_array_equal(out[f], seq.astype(float))
    assert ring.pushed == n and ring.popped == len(out) and ring.popped + ring.lost + len(ring) == n
