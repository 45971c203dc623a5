"""PoseLog: distinct poses, visits, and the Good-Turing share of rests at poses not seen yet."""

from __future__ import annotations

import numpy as np

from gyrocal.daemon.poses import PoseLog

FACES = [np.array(v, dtype=float)
         for v in ((0, 0, 1), (1, 0, 0), (0, 1, 0), (0, 0, -1), (-1, 0, 0), (0, -1, 0))]


def _rest(log: PoseLog, g: np.ndarray, blocks: int = 3) -> None:
    for _ in range(blocks):  # consecutive blocks at one pose are one visit
        log.note(g + np.random.default_rng(len(log.poses)).normal(0, 0.005, 3))


def test_a_tumble_through_new_poses_keeps_the_share_at_one() -> None:
    log = PoseLog()
    assert log.unseen_share() == 1.0
    for g in FACES:
        _rest(log, g)
    assert len(log.poses) == 6 and log.visits == [1] * 6
    assert log.unseen_share() == 1.0


def test_a_unit_cycling_through_its_poses_drives_the_share_down() -> None:
    log = PoseLog()
    for _ in range(4):
        for g in FACES:
            _rest(log, g)
    assert len(log.poses) == 6 and log.visits == [4] * 6
    assert log.unseen_share() == 1 / 25  # (N1 + 1) / (N + 1) with N1 = 0, N = 24
    _rest(log, np.array([0.6, 0.0, 0.8]))  # a new pose after 24 visits: N1 = 1
    assert log.unseen_share() == 2 / 26


def test_the_oldest_pose_is_forgotten_with_its_visits() -> None:
    log = PoseLog(max_poses=4)
    for g in FACES:
        _rest(log, g, blocks=1)
    assert len(log.poses) == 4 and len(log.visits) == 4
    np.testing.assert_allclose(log.poses[0], FACES[2], atol=0.05)
    _rest(log, FACES[5], blocks=2)  # still at the last pose: no new visit
    assert log.visits[-1] == 1
    _rest(log, FACES[2], blocks=1)  # back to the oldest kept pose
    assert log.visits[0] == 2
    assert log.array(3).shape == (4, 3)
    assert PoseLog().array(10).shape == (0, 10)
