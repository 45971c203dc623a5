"""The fast paths of the engine and readers give exactly what the plain code gives (issue 11, s8perf).

Each fast path replaced a slower formulation of the same arithmetic; these tests keep the two
side by side, bit for bit, so a later edit cannot drift from the reference.
"""

from __future__ import annotations

import numpy as np

from gyrocal.daemon.blocks import BlockAccumulator
from gyrocal.daemon.ring import SAMPLE_DTYPE
from gyrocal.model.still import StillRule, StreamingStill, _quantum, _rolling, detect_still, rolling_stats
from gyrocal.protocol.can_codec import CanCodec
from gyrocal.protocol.can_reassembly import _raw_decoder


def _rolling_1d(x: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """The reference: one column at a time, as model/still.py computed it before."""
    n = x.size
    x0 = x[0] if n else 0.0
    x = x - x0
    cs = np.concatenate(([0.0], np.cumsum(x)))
    cs2 = np.concatenate(([0.0], np.cumsum(x * x)))
    i = np.arange(n)
    lo = np.clip(i - w // 2, 0, n)
    hi = np.clip(i + w - w // 2, 0, n)
    cnt = hi - lo
    mean = (cs[hi] - cs[lo]) / cnt
    var = np.maximum((cs2[hi] - cs2[lo]) / cnt - mean**2, 0.0)
    return mean + x0, np.sqrt(var)


def _samples(n: int, seed: int = 3) -> np.ndarray:
    """Still stretches and turns at 2 kHz, accel quantised to 1 mg."""
    rng = np.random.default_rng(seed)
    b = np.zeros(n, dtype=SAMPLE_DTYPE)
    b["seq"] = np.arange(n)
    b["t"] = np.arange(n) / 2000.0
    turn = np.where((np.arange(n) // 5000) % 2 == 1, 30 * np.sin(np.arange(n) / 300), 0.0)
    for f in ("wx", "wy", "wz"):
        b[f] = rng.normal(0, 0.01, n) + turn
    for f in ("ax", "ay", "az"):
        b[f] = np.round(rng.normal(0, 0.002, n) + (f == "az"), 3)
    return b


def test_rolling_over_columns_is_the_per_column_rolling_bit_for_bit() -> None:
    b = _samples(20000)
    x = np.column_stack([b[f] for f in ("wx", "wy", "wz", "ax", "ay", "az")])
    for w in (3, 4, 400, 801, 30000):
        mean, std = _rolling(x, w)
        for k in range(6):
            m1, s1 = _rolling_1d(x[:, k], w)
            assert np.array_equal(mean[:, k], m1) and np.array_equal(std[:, k], s1)
        stats = rolling_stats(x[:, :3], x[:, 3:], w)
        assert np.array_equal(stats[:, 0:3], mean[:, :3]) and np.array_equal(stats[:, 6:9], std[:, 3:])


def test_quantum_by_sort_is_the_step_between_distinct_values() -> None:
    b = _samples(5000)
    for f in ("ax", "wx"):
        steps = np.diff(np.unique(b[f]))
        assert _quantum(b[f]) == float(steps[steps > 0].min())
    assert _quantum(np.ones(10)) == 0.0


def test_streaming_still_decides_the_same_whatever_the_block_sizes_with_a_wrapping_history() -> None:
    """memory_s = 5 s keeps 100 history rows: the circular history wraps many times."""
    b = _samples(30000)
    results = []
    for sizes in ([2000], [7, 13, 500], [4096, 3]):
        s = StreamingStill(2000.0, StillRule(memory_s=5.0))
        out, i, j = [], 0, 0
        while i < b.size:
            m = sizes[j % len(sizes)]
            out.append(s.feed(b[i:i + m]))
            i, j = i + m, j + 1
        out.append(s.feed(b[:0], final=True))
        rows = np.concatenate([o[0] for o in out])
        still = np.concatenate([o[1] for o in out])
        assert np.array_equal(rows["seq"], b["seq"])
        results.append(still)
    # levels are refreshed every 0.25 s of data whatever the blocks: same stretches found
    assert 0.3 < results[0].mean() < 0.6
    off_line = detect_still({f: b[f] for f in b.dtype.names}, 2000.0)
    assert np.mean(results[0] == off_line) > 0.99


def test_raw_can_decoder_gives_what_cantools_decode_simple_gives() -> None:
    codec = CanCodec()
    rng = np.random.default_rng(5)
    for name, message in codec.by_name.items():
        decode = _raw_decoder(message)
        for _ in range(50):
            data = bytes(rng.integers(0, 256, message.length, dtype=np.uint8))
            assert decode(data) == message.decode_simple(data, decode_choices=False, scaling=False), name


class _LoopAccumulator(BlockAccumulator):
    """The reference: the per-sample loop blocks.py used before the runs were found with numpy."""

    def feed(self, raw, out, phi, still):  # type: ignore[no-untyped-def]
        done: list = []
        train = np.zeros(still.shape[0], dtype=bool)
        i, n = 0, still.shape[0]
        while i < n:
            if not still[i]:
                self._close(done, partial=True)
                j = i + 1
                while j < n and not still[j]:
                    j += 1
                i = j
                continue
            j = i
            room = self.size - self._n
            while j < n and still[j] and j - i < room:
                j += 1
            sl = slice(i, j)
            if not self.current_is_holdout:
                train[sl] = True
            self._raw += raw[sl].sum(axis=0)
            self._out += out[sl].sum(axis=0)
            self._phi += phi[sl].sum(axis=0)
            self._n += j - i
            if self._n >= self.size:
                self._close(done, partial=False)
            i = j
        return done, train


def test_block_accumulator_cuts_the_same_blocks_as_the_per_sample_loop() -> None:
    rng = np.random.default_rng(9)
    n = 20000
    raw, out, phi = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 10))
    still = np.repeat(rng.random(400) < 0.6, rng.integers(1, 120, 400))[:n]
    still = np.concatenate([still, np.ones(n - still.size, dtype=bool)])
    for size in (2, 37, 1000):
        fast, ref = BlockAccumulator(size, 5, 10), _LoopAccumulator(size, 5, 10)
        for cut in np.split(np.arange(n), [1, 2, 500, 513, 9000, 19999]):
            sl = slice(cut[0], cut[-1] + 1) if cut.size else slice(0, 0)
            b1, t1 = fast.feed(raw[sl], out[sl], phi[sl], still[sl])
            b2, t2 = ref.feed(raw[sl], out[sl], phi[sl], still[sl])
            assert np.array_equal(t1, t2) and len(b1) == len(b2)
            for x, y in zip(b1, b2, strict=True):
                assert x.n == y.n and x.holdout == y.holdout
                for f in ("raw_dps", "out_dps", "phi"):
                    assert np.array_equal(getattr(x, f), getattr(y, f))
        assert fast.count == ref.count > 0
