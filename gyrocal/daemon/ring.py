"""A lock-free single-producer / single-consumer ring buffer of samples.

The link's reader thread is the one producer; the estimator thread is the one consumer. The reader
must never wait on the estimator, so on overflow the producer overwrites the oldest slot and the
consumer later counts what it missed: the buffer keeps the newest samples, and ``lost`` says how
many were dropped. Memory is one preallocated numpy structured array (O(1) however long it runs).

Thread-safety argument (SPSC, monotonic indices, CPython):

- ``_head`` is the count of samples ever written. Only the producer writes it, and only *after*
  the slot ``_head % capacity`` is filled; a Python int store is atomic under the GIL, and the GIL
  hand-over orders the slot write before the index store as seen by the other thread. Before it
  writes a slot the producer sets ``_claim = _head + 1``, announcing the overwrite.
- ``_tail`` is the count of samples consumed (or skipped as lost). Only the consumer writes it.
- The consumer snapshots ``head``, copies slots ``[max(tail, head - capacity), head)``, then reads
  ``_claim``. Every sample with index ``< _claim - capacity`` has been (or is being) overwritten
  since the snapshot, so it may be torn: it is discarded and counted as lost. This validation does
  not rely on the GIL being held during the copy (numpy may release it); a full ring that no one is
  writing to loses nothing.
- Neither side ever takes a lock, so ``push`` never blocks.

Counters: ``pushed`` (producer), ``popped`` and ``lost`` (consumer); at any quiescent moment
``pushed == popped + lost + len(ring)``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

SAMPLE_DTYPE = np.dtype(
    [
        ("seq", "u4"),  # the unit's sample counter
        ("t", "f8"),  # unit time [s]
        ("wx", "f8"), ("wy", "f8"), ("wz", "f8"),  # gyro [deg/s]
        ("ax", "f8"), ("ay", "f8"), ("az", "f8"),  # specific force [g]
        ("temp", "f8"),  # sensor temperature [degC]
        ("rx", "f8"),  # host receive time, time.monotonic() [s]
    ]
)
"""One sample as the ring stores it."""


class RingBuffer:
    """A preallocated SPSC ring of ``SAMPLE_DTYPE`` records that keeps the newest on overflow.

    ``capacity`` [samples]: e.g. 2 kHz x 30 s = 60000 gives the estimator 30 s of slack.
    """

    def __init__(self, capacity: int) -> None:
        if int(capacity) < 1:
            raise ValueError(f"ring capacity must be >= 1 sample, got {capacity}")
        self.capacity = int(capacity)
        self._buf = np.zeros(self.capacity, dtype=SAMPLE_DTYPE)
        self._head = 0  # written by the producer only
        self._claim = 0  # written by the producer only: _head + 1 while a slot is being written
        self._tail = 0  # written by the consumer only
        self._lost = 0  # written by the consumer only

    # ---- producer side -------------------------------------------------------------------------
    def push(self, sample: Any, rx_time: float) -> None:
        """Store one sample (a ``protocol.messages.Sample``) received at host time ``rx_time`` [s].

        Never blocks; when the ring is full the oldest sample is overwritten (counted on ``pop``).
        """
        g, a = sample.gyro_dps, sample.accel_g
        self.push_values(sample.seq, sample.t_s, g[0], g[1], g[2], a[0], a[1], a[2], sample.temp_c, rx_time)

    def push_values(
        self, seq: int, t_s: float, wx: float, wy: float, wz: float,
        ax: float, ay: float, az: float, temp_c: float, rx_time: float,
    ) -> None:
        """Store one sample given as numbers (same units as ``SAMPLE_DTYPE``). Never blocks."""
        head = self._head
        self._claim = head + 1  # announce the write first: the consumer checks it after copying
        self._buf[head % self.capacity] = (seq & 0xFFFFFFFF, t_s, wx, wy, wz, ax, ay, az, temp_c, rx_time)
        self._head = head + 1  # publish after the slot is written

    def push_block(self, block: np.ndarray) -> None:
        """Store many samples at once (a ``SAMPLE_DTYPE`` array, at most ``capacity``); never blocks.

        The same protocol as ``push``, for a producer that has a block in hand (``gyrocal replay``).
        """
        n = int(block.size)
        if n == 0:
            return
        if n > self.capacity:
            raise ValueError(f"a block of {n} samples does not fit a ring of {self.capacity}")
        head = self._head
        self._claim = head + n
        i = head % self.capacity
        first = min(n, self.capacity - i)
        self._buf[i : i + first] = block[:first]
        if first < n:
            self._buf[: n - first] = block[first:]
        self._head = head + n

    # ---- consumer side -------------------------------------------------------------------------
    def pop(self, max_n: int | None = None) -> np.ndarray:
        """Take up to ``max_n`` of the oldest unread samples (all when None), oldest first.

        Returns a new structured array (dtype ``SAMPLE_DTYPE``) that the caller owns; it may be
        empty. Samples overwritten before they could be read are added to ``lost``.
        """
        tail, head = self._tail, self._head
        start = max(tail, head - self.capacity)  # older ones were overwritten: lost
        end = head if max_n is None else min(head, start + max(0, int(max_n)))
        out = self._copy(start, end)
        safe = self._claim - self.capacity  # indices below this were (or are being) overwritten
        first_kept = min(max(start, safe), end)
        if first_kept > start:
            out = out[first_kept - start :]
        self._lost += first_kept - tail
        self._tail = end
        return out

    def _copy(self, start: int, end: int) -> np.ndarray:
        n = end - start
        out = np.empty(max(n, 0), dtype=SAMPLE_DTYPE)
        if n <= 0:
            return out
        i = start % self.capacity
        first = min(n, self.capacity - i)
        out[:first] = self._buf[i : i + first]
        if first < n:
            out[first:] = self._buf[: n - first]
        return out

    def wait(self, timeout_s: float, min_n: int = 1, poll_s: float = 0.002) -> bool:
        """Poll (never lock) until ``min_n`` samples are readable or ``timeout_s`` [s] passes."""
        deadline = time.monotonic() + timeout_s
        while len(self) < min_n:
            if time.monotonic() >= deadline:
                return False
            time.sleep(poll_s)
        return True

    # ---- counters ------------------------------------------------------------------------------
    def __len__(self) -> int:
        """Samples readable now (at most ``capacity``)."""
        return min(self._head - self._tail, self.capacity)

    @property
    def pushed(self) -> int:
        """Samples ever pushed."""
        return self._head

    @property
    def popped(self) -> int:
        """Samples ever returned by ``pop``."""
        return self._tail - self._lost

    @property
    def position(self) -> int:
        """Index (in push order) of the next sample ``pop`` will return: popped plus lost."""
        return self._tail

    @property
    def lost(self) -> int:
        """Samples overwritten before the consumer read them (including those not yet noticed)."""
        return self._lost + max(0, self._head - self._tail - self.capacity)

    def stats(self) -> dict[str, int]:
        return {"capacity": self.capacity, "pushed": self.pushed, "popped": self.popped,
                "lost": self.lost, "fill": len(self)}
