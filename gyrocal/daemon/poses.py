"""The distinct poses a session has seen at rest, and how often the unit came back to each.

The push gate must predict the drift a set leaves at the poses where the unit will be judged, and
the daemon sees only some of them. How many it has not seen yet it cannot know, but it can estimate
the share of the unit's rests that fall at poses not seen yet from how often the unit comes back to
the poses it has seen: Good-Turing's estimate of the unseen mass, (N1 + 1) / (N + 1), over N still
visits of which N1 went to poses visited only once. A unit that tumbles through new orientations
keeps the share at 1 (the sphere of gravity directions decides); one that cycles through a fixed
set of poses drives it towards 0 (those poses decide). A pose is a block's mean terms (gravity
direction, and the other inputs such as temperature), within ``tol`` of one seen before.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PoseLog:
    """Poses seen (block-mean terms (P,)), with the number of still visits to each."""

    max_poses: int = 64
    """Beyond this many, the older of the two closest poses is merged into the other (its visits with
    it), so the memory keeps covering everything seen: a warm-up's first degrees stay among the poses
    at its end (dropping the oldest pose kept only the last 32 s of one)."""
    tol: float = 0.05
    """Largest difference of any term (gravity components [g]) within which a block is at a seen pose."""
    poses: list[np.ndarray] = field(default_factory=list)
    visits: list[int] = field(default_factory=list)
    _last: int | None = None  # index of the last still block's pose: consecutive blocks are one visit

    def note(self, phi: np.ndarray) -> None:
        """One still block's mean terms: a new pose, another block of this visit, or a return."""
        dist = [float(np.max(np.abs(phi - p))) for p in self.poses]
        i = int(np.argmin(dist)) if dist and min(dist) <= self.tol else None
        if i is None:
            self.poses.append(np.array(phi, dtype=float))
            self.visits.append(1)
            i = len(self.poses) - 1
            if len(self.poses) > self.max_poses:
                old, keep = _closest_pair(np.array(self.poses))
                self.visits[keep] += self.visits[old]
                self.poses.pop(old)
                self.visits.pop(old)
                i -= 1  # the new pose is the last, never the older of a pair
        elif i != self._last:
            self.visits[i] += 1
        self._last = i

    def array(self, n_terms: int) -> np.ndarray:
        """The poses seen as (K, P); (0, P) before the first."""
        return np.array(self.poses) if self.poses else np.zeros((0, n_terms))

    def unseen_share(self) -> float:
        """The share of the unit's rests at poses not seen yet (Good-Turing), in (0, 1].

        A rest split by a short move counts as one visit (the cautious side: fewer returns). The
        +1 keeps the share above 0 however often the poses repeat, and at 1 before the first visit.
        """
        n = sum(self.visits)
        n1 = sum(1 for v in self.visits if v == 1)
        return min(1.0, (n1 + 1) / (n + 1))


def _closest_pair(poses: np.ndarray) -> tuple[int, int]:
    """Indices (older, newer) of the closest pair in (K, P) ``poses``, each term scaled by its span."""
    span = np.ptp(poses, axis=0)
    z = poses / np.where(span > 0, span, 1.0)
    d = np.linalg.norm(z[:, None, :] - z[None, :, :], axis=2)
    d[np.diag_indices_from(d)] = np.inf
    i, j = np.unravel_index(int(np.argmin(d)), d.shape)
    return int(min(i, j)), int(max(i, j))
