"""Still blocks: the daemon's unit of evidence for validation and monitoring.

The per-sample white noise of a gyro (0.002 deg/s in the virtual unit, 0.3 deg/s on an MEMS part)
hides the drift a calibration removes. Averaging each still stretch over ``block_s`` seconds keeps
the drift and shrinks the noise by sqrt(n), which is what a navigation user cares about (the bias
error, not the per-sample noise; cf. Contract 2's tau_s). Because the model is linear in its terms,
the block mean of ``C @ phi`` is ``C @ mean(phi)``: a block needs only its means to test any set.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Block:
    """Means over one still block: raw rate [deg/s] (3,), output rate [deg/s] (3,), terms (P,), and
    the raw rate's noise variance per sample within the block [(deg/s)^2] (3,), from successive
    differences (half their mean square), so that a drift or a temperature change inside the block
    is not taken for noise. The mean keeps var / n of it (white noise; more when it is coloured)."""

    raw_dps: np.ndarray
    out_dps: np.ndarray
    phi: np.ndarray
    n: int
    holdout: bool
    raw_var_dps2: np.ndarray = field(default_factory=lambda: np.zeros(3))


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
        self._dsq = np.zeros(3)  # sum of squared successive differences of raw [(deg/s)^2]
        self._nd = 0
        self._last: np.ndarray | None = None  # the block's newest raw sample [deg/s]
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
                x = raw[sl]
                self._raw += x.sum(axis=0)
                d = np.diff(x if self._last is None else np.vstack([self._last, x]), axis=0)
                self._dsq += np.square(d).sum(axis=0)
                self._nd += d.shape[0]
                self._last = x[-1]
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
            var = self._dsq / (2 * self._nd) if self._nd else np.zeros(3)
            done.append(Block(self._raw / n, self._out / n, self._phi / n, n, self.current_is_holdout, var))
            self.count += 1
        self._reset(self._phi.shape[0])


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

    def rms_out(self) -> np.ndarray:
        """RMS over blocks of the unit's output mean [deg/s], per axis: the drift left in the output."""
        if not self.blocks:
            return np.full(3, np.nan)
        out = np.array([b.out_dps for b in self.blocks])
        return np.sqrt(np.mean(out**2, axis=0))

    def noise_var(self) -> np.ndarray:
        """The white-noise variance of a block mean [(deg/s)^2], per axis: the median over blocks of
        var / n (a median, so that a few blocks with a vibration or the edge of a move in them do
        not raise it).

        Part of every held-out RMS whatever set is tested, so it is what a calibration can never
        remove. On an MEMS unit (0.05 deg/s per sample, 0.5 s blocks at 100 Hz) it is 25 deg/h, more
        than the drift a push removes. It reads low when the noise is coloured (neighbouring samples
        alike), which only makes a gate that subtracts it stricter.
        """
        if not self.blocks:
            return np.full(3, np.nan)
        return np.median([b.raw_var_dps2 / b.n for b in self.blocks], axis=0)

    def sq_residuals(self, coeffs_dps: np.ndarray | None) -> np.ndarray:
        """Per block, the squared residual summed over the axes [(deg/s)^2] (B,): raw minus what
        ``coeffs_dps`` (3, P) would apply, or the unit's output when ``coeffs_dps`` is None."""
        if coeffs_dps is None:
            res = np.array([b.out_dps for b in self.blocks])
        else:
            raw = np.array([b.raw_dps for b in self.blocks])
            phi = np.array([b.phi for b in self.blocks])
            res = raw - phi @ np.asarray(coeffs_dps).T
        return np.sum(res**2, axis=1)

    def rms_with(self, coeffs_dps: np.ndarray) -> np.ndarray:
        """RMS over blocks of raw minus the compensation ``coeffs_dps`` (3, P) would apply [deg/s]."""
        if not self.blocks:
            return np.full(3, np.nan)
        raw = np.array([b.raw_dps for b in self.blocks])
        phi = np.array([b.phi for b in self.blocks])
        res = raw - phi @ np.asarray(coeffs_dps).T
        return np.sqrt(np.mean(res**2, axis=0))


NOISE_SHARE_MIN = 0.2
"""The systematic gate applies only where the blocks' noise is at least this share of the current
set's mean squared held-out residual. Below it the plain gate is nearly the systematic one and stays
in charge alone, as before 2026-11-26: a low-noise unit (a fibre-optic gyro) pushes exactly as it did."""

GAIN_Z = 3.0
"""How many standard errors the held-out gain must clear when the block noise is subtracted (one-sided
p about 0.001 for independent blocks; held-out blocks of one rest are alike, so it is kept strict)."""


@dataclass
class HeldOutGain:
    """A new set against the current one on held-out blocks, with the blocks' noise taken out.

    Why: the plain gate (the held-out RMS falls by ``min_improvement``) compares totals that both
    hold the block means' noise. On a unit whose noise per block is larger than its drift (an MEMS
    part at 0.05 deg/s per sample) no set can cut the total by 20 %, and the unit was never calibrated:
    the daemon on bench_bias_state's walk + flicker unit pushed nothing in 10 minutes. Here the
    systematic part (total minus noise) must fall by the same fraction, and the paired per-block
    gain must be significant, so noise alone never passes.
    """

    old2: float  # mean over blocks of the squared residual, summed over the axes [(deg/s)^2]
    new2: float
    noise2: float  # the block means' noise variance, summed over the axes [(deg/s)^2]
    z: float  # the paired gain in standard errors (0 with fewer than 3 blocks)
    blocks: int

    def passes(self, need: float) -> bool:
        """True when the systematic part's square falls to ``need`` x its old value, significantly,
        on blocks where the noise is a sizeable part of the residual (``NOISE_SHARE_MIN``)."""
        sys_old = self.old2 - self.noise2
        return (self.blocks >= 3 and self.noise2 >= NOISE_SHARE_MIN * self.old2 and sys_old > 0
                and max(self.new2 - self.noise2, 0.0) <= need * sys_old and self.z >= GAIN_Z)

    def systematic_dps(self) -> tuple[float, float]:
        """The held-out RMS without the noise [deg/s], current and new (0 where noise explains all)."""
        return (float(np.sqrt(max(self.old2 - self.noise2, 0.0))),
                float(np.sqrt(max(self.new2 - self.noise2, 0.0))))


def held_out_gain(window: BlockWindow, old_coeffs_dps: np.ndarray | None,
                  new_coeffs_dps: np.ndarray) -> HeldOutGain:
    """Compare ``new_coeffs_dps`` (3, P) with ``old_coeffs_dps`` (None: the unit's output) on ``window``."""
    sq_old, sq_new = window.sq_residuals(old_coeffs_dps), window.sq_residuals(new_coeffs_dps)
    d = sq_old - sq_new
    b = int(d.size)
    z = 0.0
    if b >= 3:
        se = float(np.std(d, ddof=1)) / np.sqrt(b)
        z = float(np.mean(d)) / se if se > 0 else (np.inf if np.mean(d) > 0 else 0.0)
    return HeldOutGain(float(np.mean(sq_old)) if b else np.nan, float(np.mean(sq_new)) if b else np.nan,
                       float(np.sum(window.noise_var())) if b else np.nan, z, b)
