"""The bias step check over still blocks (gyrocal/daemon/stepcheck.py), on blocks made here."""

from __future__ import annotations

import numpy as np

from gyrocal.daemon.blocks import Block
from gyrocal.daemon.stepcheck import find_step

DPH = 3600.0
COEFFS = np.array([[0.01, 0.002, -0.001, 0.0005], [-0.02, 0.001, 0.003, 0.0], [0.005, 0.0, 0.001, -0.002]])


def _blocks(rng: np.random.Generator, nb: int, noise_dph: float = 0.5, walk_dph: float = 0.0,
            steps: tuple[tuple[int, int, float], ...] = ()) -> list[Block]:
    """``nb`` blocks of 0.5 s (200 samples) at random gravity directions, the model's drift plus white
    noise of ``noise_dph`` per block, a walk of ``walk_dph`` per block on every axis, and each
    (block, axis, deg/h) of ``steps`` from that block on."""
    out, walk = [], np.zeros(3)
    for i in range(nb):
        g = rng.normal(size=3)
        phi = np.r_[1.0, g / np.linalg.norm(g)]
        walk = walk + rng.normal(0.0, walk_dph / DPH, 3)
        raw = COEFFS @ phi + rng.normal(0.0, noise_dph / DPH, 3) + walk
        for at, axis, dph in steps:
            if i >= at:
                raw[axis] += dph / DPH
        out.append(Block(raw, raw, phi, 200, False, 0.5 * (i + 1)))
    return out


def test_a_lone_step_is_found_with_its_axis_size_and_time() -> None:
    rng = np.random.default_rng(1)
    step = find_step(_blocks(rng, 60, steps=((30, 1, -60.0),)))
    assert step is not None and step.axis == 1 and step.after == 30
    assert abs(step.dps * DPH + 60.0) < 1.0 and step.t_s == 15.5


def test_white_noise_and_a_modest_walk_give_no_step() -> None:
    """No step in 40 null windows of 200 blocks, white, nor with a walk of 0.2 deg/h per block (13
    deg/h/sqrt(h) at 0.5 s blocks, a fibre unit's wander many times over)."""
    rng = np.random.default_rng(2)
    assert [find_step(_blocks(rng, 200)) for _ in range(20)] == [None] * 20
    assert [find_step(_blocks(rng, 200, walk_dph=0.2)) for _ in range(20)] == [None] * 20


def test_a_step_below_the_floor_or_the_blocks_scatter_is_not_believed() -> None:
    """5 deg/h is below the alarm floor (7.2); 60 deg/h in white block noise of 40 deg/h (an MEMS
    unit's) is below 4 times the scatter, however many blocks show it."""
    rng = np.random.default_rng(3)
    assert find_step(_blocks(rng, 60, steps=((30, 0, 5.0),))) is None
    assert find_step(_blocks(rng, 400, noise_dph=40.0, steps=((200, 0, 60.0),))) is None


def test_a_step_needs_8_blocks_after_it_and_one_before() -> None:
    """One block before it is enough: a warm unit whose bias stepped 1 s after switch-on (2 still
    blocks before) could not be placed with 3 required, and its bias stages left x 2.4-3.6 deg/h
    for good where 0.1 is usual, after 16-20 s over 10 deg/h with the alarm off (in process)."""
    rng = np.random.default_rng(4)
    assert find_step(_blocks(rng, 40, steps=((35, 0, 60.0),))) is None  # 5 blocks after it
    step = find_step(_blocks(rng, 40, steps=((1, 0, 60.0),)))
    assert step is not None and step.axis == 0 and step.after == 39 and abs(step.dps * DPH - 60.0) < 2.0
    assert find_step(_blocks(rng, 40, steps=((0, 0, 60.0),))) is None  # the bias was the same all along


def test_a_vehicle_settling_is_not_taken_for_a_step() -> None:
    """Blocks as a vehicle settling 0.3 deg in steps of 0.06 deg gave them (in process, unit seed 3):
    3 of the 4 before the settling ended held the slow turn's rate (198 deg/h, too slow for the still
    rule) at tilts 0.005 g apart. 10 free gravity terms fitted those 4 exactly, and a trim over both
    sides left out the 3: the settling was taken for a 189 deg/h step of x."""
    rng = np.random.default_rng(5)
    names_phi = []
    for i in range(30):
        gy = -0.00525 if i >= 4 else -0.0016 * i
        g = np.array([0.0, gy, np.sqrt(1 - gy**2)])
        names_phi.append(np.r_[1.0, g, g**2, g[0] * g[1], g[1] * g[2], g[0] * g[2]])
    blocks = []
    for i, phi in enumerate(names_phi):
        raw = np.array([-2.5, -33.8, 13.4]) / DPH + rng.normal(0.0, 0.5 / DPH, 3)
        if i in (1, 2, 3):
            raw[0] -= 196.0 / DPH  # the turn's true rate in the block
        blocks.append(Block(raw, raw, phi, 200, False, 0.5 * (i + 1)))
    assert find_step(blocks) is None
    # the same blocks with a real step of x after the settling, and clean rests before it
    for i, b in enumerate(blocks):
        if i in (1, 2, 3):
            b.raw_dps[0] += 196.0 / DPH
        if i >= 4:
            b.raw_dps[0] += 60.0 / DPH
    step = find_step(blocks)
    assert step is not None and step.axis == 0 and abs(step.dps * DPH - 60.0) < 3.0
