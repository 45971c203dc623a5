"""Telling a unit restart from an outlier in the sample sequence.

Why: the unit numbers its samples from 0 at every switch-on, so a sequence number that goes far
back *suggests* a restart. But one CRC-valid sample with a far sequence number (a unit's glitch, a
bit flip the CRC did not catch, a frame from a replayed log) must not end a session and throw away
its learning. So a jump is only a *candidate*: its samples are held back, and the candidate is

- **confirmed** when ``confirm_n`` samples in a row continue it (a new numbering really began):
  a jump back is a restart (new session unless a HELLO already started one); a jump forward is a
  gap (samples lost or the unit silent), same session;
- **rejected** as outliers when the stream continues the old numbering: its samples are dropped
  and counted (``outliers``), and the session never noticed.

A HELLO is stronger evidence than the sequence: the engine calls :meth:`expect_restart` when a HELLO
starts a session, and then the next jump is the new numbering at once, with no second session.

Pure logic, vectorised over a block; only the (rare) discontinuities are walked in Python.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from gyrocal.protocol.messages import SEQ_MODULO

log = logging.getLogger("gyrocal.restart")


def _forward(a: int, b: int) -> int:
    """How far b is after a (mod 2^32), as a signed distance in (-2^31, 2^31]."""
    d = (b - a) % SEQ_MODULO
    return d - SEQ_MODULO if d > SEQ_MODULO // 2 else d


@dataclass
class SeqTracker:
    """Splits sample blocks into ("same", block) and ("restart", block) parts; see module doc.

    ``far``: a jump of more than this many samples (back, or forward) is a candidate.
    ``confirm_n``: consecutive samples that confirm a candidate.
    """

    far: int = 1000
    confirm_n: int = 32
    last: int | None = None
    outliers: int = 0
    restarts: int = 0
    gaps: int = 0
    _cand: list[np.ndarray] = field(default_factory=list)
    _cand_last: int = 0
    _expect: bool = False

    @property
    def pending(self) -> int:
        """Samples held back in an unconfirmed candidate."""
        return int(sum(c.size for c in self._cand))

    def expect_restart(self) -> np.ndarray | None:
        """A HELLO began a new switch-on: the next jump is its numbering. Returns the held candidate's
        samples (they already belong to the new session), or None."""
        held = self._take() if self._cand else None
        if held is not None:
            self.last = int(held["seq"][-1])
        else:
            self._expect = True
        return held

    def feed(self, block: np.ndarray) -> list[tuple[str, np.ndarray]]:
        out: list[tuple[str, np.ndarray]] = []
        if block.size == 0:
            return out
        seq = block["seq"].astype(np.int64)
        cuts = np.flatnonzero((np.diff(seq) % SEQ_MODULO) != 1) + 1
        for seg in np.split(block, cuts):
            self._segment(seg, out)
        return out

    def _segment(self, seg: np.ndarray, out: list[tuple[str, np.ndarray]]) -> None:
        first, lastv = int(seg["seq"][0]), int(seg["seq"][-1])
        if self.last is None:
            self.last, self._expect = lastv, False
            out.append(("same", seg))
            return
        d_main = _forward(self.last, first)
        if self._cand:
            if 0 < _forward(self._cand_last, first) <= self.far:
                self._cand.append(seg)
                self._cand_last = lastv
                self._maybe_confirm(out)
                return
            if -self.far <= d_main <= self.far:  # the old numbering goes on: the candidate was noise
                n = self.pending
                self.outliers += n
                log.warning("dropped %d sample(s) with a far sequence number (%d): outlier, not a restart",
                            n, int(self._cand[0]["seq"][0]))
                self._cand = []
            else:  # another jump: the older candidate was noise
                self.outliers += self.pending
                self._cand = []
        if -self.far <= d_main <= self.far and not self._expect:
            # a few lost samples (the decoder counts them) or a repeat: the same numbering
            if _forward(self.last, lastv) > 0:
                self.last = lastv
            out.append(("same", seg))
            return
        if self._expect:  # a HELLO said so: this is the new numbering
            self._expect = False
            self.last = lastv
            out.append(("same", seg))
            return
        self._cand = [seg]
        self._cand_last = lastv
        self._maybe_confirm(out)

    def _maybe_confirm(self, out: list[tuple[str, np.ndarray]]) -> None:
        if self.pending < self.confirm_n:
            return
        held = self._take()
        back = _forward(self.last or 0, int(held["seq"][0])) < 0
        self.last = int(held["seq"][-1])
        if back:
            self.restarts += 1
            out.append(("restart", held))
        else:
            self.gaps += 1
            out.append(("same", held))

    def _take(self) -> np.ndarray:
        held = np.concatenate(self._cand) if len(self._cand) > 1 else self._cand[0]
        self._cand = []
        return held
