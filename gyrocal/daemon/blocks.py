"""Still blocks: the daemon's unit of evidence for validation and monitoring.

The per-sample white noise of a gyro (0.002 deg/s in the virtual unit, 0.3 deg/s on an MEMS part)
hides the drift a calibration removes. Averaging each still stretch over ``block_s`` seconds keeps
the drift and shrinks the noise by sqrt(n), which is what a navigation user cares about (the bias
error, not the per-sample noise; cf. Contract 2's tau_s). Because the model is linear in its terms,
the block mean of ``C @ phi`` is ``C @ mean(phi)``: a block needs only its means to test any set.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass
class Block:
    """Means over one still block: raw rate [deg/s] (3,), output rate [deg/s] (3,), terms (P,)."""

    raw_dps: np.ndarray
    out_dps: np.ndarray
    phi: np.ndarray
    n: int
    holdout: bool
    t_s: float = float("nan")  # the unit's time stamp [s] of the batch that closed it (set by the session)


class BlockAccumulator:
    """Cuts the still samples into blocks of ``size`` samples; a break in stillness ends a block.

    Every ``holdout_every``-th block is marked holdout: its samples are kept out of training so the
    validation step can judge a coefficient set on data the estimator did not see.
    """

    def __init__(self, size: int, holdout_every: int, n_terms: int) -> None:
        self.size = max(2, size)
        self.holdout_every = holdout_every
        self.count = 0
        self._reset(n_terms)

    def _reset(self, n_terms: int) -> None:
        self._raw = np.zeros(3)
        self._out = np.zeros(3)
        self._phi = np.zeros(n_terms)
        self._n = 0

    @property
    def current_is_holdout(self) -> bool:
        return self.count % self.holdout_every == self.holdout_every - 1

    def feed(
        self, raw: np.ndarray, out: np.ndarray, phi: np.ndarray, still: np.ndarray,
    ) -> tuple[list[Block], np.ndarray]:
        """Add samples; return the blocks completed and a mask of samples that may be trained on.

        raw, out: (N, 3) deg/s; phi: (N, P); still: (N,) bool. Non-still samples end a block (a
        partial block of at least half the size is kept) and are never trained on.
        """
        done: list[Block] = []
        n = still.shape[0]
        train = np.zeros(n, dtype=bool)
        if n == 0:
            return done, train
        # runs of equal flags found by numpy; the loop below goes per run and per block, not per sample
        edges = np.flatnonzero(still[1:] != still[:-1]) + 1
        for s, e in zip([0, *edges.tolist()], [*edges.tolist(), n], strict=True):
            if not still[s]:
                self._close(done, partial=True)
                continue
            i = s
            while i < e:
                j = min(e, i + self.size - self._n)
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

    def discard_partial(self) -> None:
        """Drop the block being filled (its samples are already trained on or held out)."""
        self._reset(self._phi.shape[0])

    def _close(self, done: list[Block], partial: bool) -> None:
        if self._n == 0:
            return
        if not partial or self._n >= self.size // 2:
            n = self._n
            done.append(Block(self._raw / n, self._out / n, self._phi / n, n, self.current_is_holdout))
            self.count += 1
        self._reset(self._phi.shape[0])


def kept_blocks(score: np.ndarray, trim: float) -> np.ndarray:
    """Indices of the blocks kept when the share ``trim`` with the largest ``score`` (B,) is left out,
    from 4 blocks on (all of them below)."""
    drop = int(trim * len(score)) if len(score) >= 4 else 0
    return np.argsort(score, kind="stable")[:len(score) - drop] if drop else np.arange(len(score))


class BlockWindow:
    """The newest blocks, bounded in number (O(1) memory however long the daemon runs)."""

    def __init__(self, maxlen: int) -> None:
        self.blocks: deque[Block] = deque(maxlen=max(1, maxlen))

    def add(self, blocks: list[Block]) -> None:
        self.blocks.extend(blocks)

    def clear(self) -> None:
        self.blocks.clear()

    def __len__(self) -> int:
        return len(self.blocks)

    def since(self, t_s: float) -> BlockWindow:
        """The blocks closed at or after ``t_s`` [s] (the unit's clock), oldest first, as a new window."""
        out = BlockWindow(len(self.blocks))
        out.add([b for b in self.blocks if b.t_s >= t_s])
        return out

    def residuals(self, coeffs_dps: np.ndarray | None) -> np.ndarray:
        """Per block (B, 3) [deg/s]: raw minus what ``coeffs_dps`` (3, P) would apply, or the unit's
        output as sent when ``coeffs_dps`` is None."""
        if coeffs_dps is None:
            return np.array([b.out_dps for b in self.blocks])
        raw = np.array([b.raw_dps for b in self.blocks])
        phi = np.array([b.phi for b in self.blocks])
        return raw - phi @ np.asarray(coeffs_dps).T

    def rms_out(self) -> np.ndarray:
        """RMS over blocks of the unit's output mean [deg/s], per axis: the drift left in the output."""
        return self.rms_with(None)

    def rms_with(self, coeffs_dps: np.ndarray | None, trim: float = 0.0) -> np.ndarray:
        """RMS over blocks of raw minus the compensation ``coeffs_dps`` (3, P) would apply [deg/s]
        (None: of the unit's output as sent); ``trim``: the share of blocks left out, those whose
        residual is largest (by its norm over the axes), from 4 blocks on."""
        if not self.blocks:
            return np.full(3, np.nan)
        r = self.residuals(coeffs_dps)
        r = r[kept_blocks(np.linalg.norm(r, axis=1), trim)]
        return np.sqrt(np.mean(r**2, axis=0))

    def paired_rms(self, old_coeffs_dps: np.ndarray | None, new_coeffs_dps: np.ndarray | None,
                   trim: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """RMS over the same blocks of raw minus what ``old_coeffs_dps`` and ``new_coeffs_dps`` (3, P)
        would apply [deg/s], per axis (None: the unit's output as sent); ``trim``: the share of blocks
        left out, those whose residual is largest under the better of the two sets (the smaller norm
        over the axes), from 4 blocks on.

        Why the better of the two: a block that neither set explains (a slow turn taken for rest, its
        true rate in the block) says nothing about which set is better, and it swamped both totals (a
        refinement refused quoting 64-93 deg/h where the unit left 0.02-0.2). A block where one set is
        wrong and the other right keeps its weight, whichever set is wrong."""
        if not self.blocks:
            return np.full(3, np.nan), np.full(3, np.nan)
        old, new = self.residuals(old_coeffs_dps), self.residuals(new_coeffs_dps)
        kept = kept_blocks(np.minimum(np.linalg.norm(old, axis=1), np.linalg.norm(new, axis=1)), trim)
        old, new = old[kept], new[kept]
        return np.sqrt(np.mean(old**2, axis=0)), np.sqrt(np.mean(new**2, axis=0))

    def paired_gain_z(self, old_coeffs_dps: np.ndarray | None, new_coeffs_dps: np.ndarray) -> float:
        """How many standard errors the new set's gain is, paired per block: the mean over blocks of
        the squared residual (summed over the axes) with ``old_coeffs_dps`` (3, P) minus with
        ``new_coeffs_dps``, over its standard error (0 with fewer than 3 blocks). None for the old set
        means the unit's output as sent.

        Why paired: both residuals of a block hold the same noise and the same bias wander, which
        cancel in the difference but for a cross term of zero mean; a wander that dominates both
        totals (an MEMS unit's flicker) then still leaves the difference its significance.
        """
        if len(self.blocks) < 3:
            return 0.0
        old, new = self.residuals(old_coeffs_dps), self.residuals(new_coeffs_dps)
        d = np.sum(old**2, axis=1) - np.sum(new**2, axis=1)
        se = float(np.std(d, ddof=1)) / np.sqrt(d.size)
        if se <= 0:
            return float("inf") if float(np.mean(d)) > 0 else 0.0
        return float(np.mean(d)) / se
