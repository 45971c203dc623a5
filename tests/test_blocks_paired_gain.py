"""The paired held-out gain (blocks.BlockWindow.paired_gain_z) and the recent blocks (``since``).

Why: on a unit whose bias wanders, the noise and the wander sit in every held-out block, so a good
set cannot cut the total RMS by 20 %; validation then asks for a significant paired gain on the
blocks of the last push.wander_horizon_s (session.py). It must not pass sets that are no better.
"""

from __future__ import annotations

import numpy as np

from gyrocal.daemon.blocks import Block, BlockWindow

DPH = 1 / 3600.0


def _window(rng: np.random.Generator, c_true: np.ndarray, noise_dps: float, wander_dps: float,
            n_blocks: int, per_block: int = 50) -> BlockWindow:
    """Held-out block means at random poses: C_true @ phi + a common wander + white noise [deg/s]."""
    win = BlockWindow(10_000)
    wander = np.cumsum(rng.normal(0.0, wander_dps / np.sqrt(n_blocks), (n_blocks, 3)), axis=0)
    for k in range(n_blocks):
        g = rng.normal(size=3)
        phi = np.r_[1.0, g / np.linalg.norm(g)]
        raw = c_true @ phi + wander[k] + rng.normal(0.0, noise_dps / np.sqrt(per_block), 3)
        win.add([Block(raw, raw, phi, per_block, True, float(k))])
    return win


def test_a_set_that_removes_the_drift_is_significant_beside_noise_and_wander() -> None:
    """10 deg/h per term against 25 deg/h of block noise and 15 deg/h of wander, 200 held-out blocks:
    over 40 units the plain ratio (the total RMS falls 20 %) is met on 1, the paired gain reaches 3
    standard errors on 31."""
    plain = significant = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        c_true = rng.normal(0.0, 10 * DPH, (3, 4))
        win = _window(rng, c_true, 0.05, 15 * DPH, 200)
        old2, new2 = np.sum(win.rms_out() ** 2), np.sum(win.rms_with(c_true) ** 2)
        plain += new2 <= 0.64 * old2
        significant += win.paired_gain_z(None, c_true) >= 3.0
    assert plain <= 4 and significant >= 26, (plain, significant)


def test_sets_no_better_are_not_significant() -> None:
    """Noise alone does not pass: the unit holds the truth and the new set is off it, or the two sets
    are off the truth by the same amount in opposite directions. At most 1 % of 400 reach 3 standard
    errors. (With a wander, a set whose constant is nearer the wander's mean over the blocks does fit
    them better: that is a real gain on the data, not noise.)"""
    passed = 0
    for seed in range(200):
        rng = np.random.default_rng(1000 + seed)
        c_true = rng.normal(0.0, 30 * DPH, (3, 4))
        win = _window(rng, c_true, 0.05, 0.0, 100)
        passed += win.paired_gain_z(c_true, c_true + rng.normal(0.0, 3 * DPH, c_true.shape)) >= 3.0
        off = rng.normal(0.0, 10 * DPH, c_true.shape)
        passed += win.paired_gain_z(c_true + off, c_true - off) >= 3.0
    assert passed <= 4, passed


def test_since_keeps_the_recent_blocks_in_order() -> None:
    win = _window(np.random.default_rng(3), np.zeros((3, 4)), 0.05, 0.0, 10)
    recent = win.since(6.0)
    assert [b.t_s for b in recent.blocks] == [6.0, 7.0, 8.0, 9.0]
    assert len(win.since(float("nan"))) == 0 and win.paired_gain_z(None, np.zeros((3, 4))) == 0.0
