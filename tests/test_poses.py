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


def test_past_the_limit_the_closest_pair_merges_and_the_first_poses_stay() -> None:
    log = PoseLog(max_poses=3)
    for x in (0.0, 1.0, 2.0, 2.1):  # one term, e.g. a warm-up's temperature: the end crowds
        log.note(np.array([x, 1.0]))
    assert [float(p[0]) for p in log.poses] == [0.0, 1.0, 2.1]  # 2.0 merged into 2.1, not 0.0 dropped
    assert log.visits == [1, 1, 2]  # the merged pose's visit goes with it
    log.note(np.array([2.1, 1.0]))  # still at the last pose: no new visit
    assert log.visits == [1, 1, 2]
    log.note(np.array([0.0, 1.0]))  # back to the first
    assert log.visits == [2, 1, 2]
    assert log.array(2).shape == (3, 2)
    assert PoseLog().array(10).shape == (0, 10)
