"""Orientation schedules for the virtual unit: static poses joined by constant-rate rotations.

Seed 000's coefficients are only determined when gravity visits enough directions: the linear terms
need +-x, +-y, +-z, and the cross terms (gx*gy, ...) need poses between the axes. The default tumble
visits the 6 faces and 12 edges of a cube (18 poses), which excites every combination the 10-term
model can separate (rank 9, see model/identifiability).

Geometry: ``gravity_g`` is the specific force a still accelerometer reads in the body frame
(unit vector, z up reads +1 on az). Between poses the body turns at a constant rate about the axis
normal to both poses, so the gyro sees a true rate and the accelerometer follows a great circle.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from gyrocal.errors import ConfigError

_EDGE = 1.0 / np.sqrt(2.0)


@dataclass(frozen=True)
class Schedule:
    """A cyclic schedule: dwell ``dwell_s`` [s] at each pose, then rotate for ``move_s`` [s]."""

    poses_g: np.ndarray  # (K, 3) unit specific-force vectors in the body frame [g]
    dwell_s: float
    move_s: float

    @property
    def segment_s(self) -> float:
        return self.dwell_s + self.move_s

    @property
    def cycle_s(self) -> float:
        return self.segment_s * len(self.poses_g)

    def motion(self, t_on_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per sample at t_on [s]: the segment since switch-on (N,) (pose k = segment % K), the axis
        (N, 3) and angle [rad] (N,) of that segment's turn so far, and the whole turn's angle (N,).

        A vector fixed on the Earth (gravity, north, the Earth's rotation) seen from the body at the
        start of the segment turns into ``_rotate(v, axis, phi)``."""
        t = np.asarray(t_on_s, dtype=np.float64)
        n_pose = len(self.poses_g)
        seg = (t // self.segment_s).astype(np.int64)
        k = seg % n_pose
        tau = t - seg * self.segment_s
        axis, angle = _rotation_between(self.poses_g[k], self.poses_g[(k + 1) % n_pose])
        frac = np.clip((tau - self.dwell_s) / max(self.move_s, 1e-9), 0.0, 1.0)
        phi = np.where(tau > self.dwell_s, frac * angle, 0.0)
        return seg, axis, phi, angle

    def state(self, t_on_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gravity [g] (N,3), true body rate [deg/s] (N,3) and a still flag (N,) at t_on [s]."""
        t = np.asarray(t_on_s, dtype=np.float64) % self.cycle_s
        k = np.minimum((t // self.segment_s).astype(int), len(self.poses_g) - 1)
        tau = t - k * self.segment_s
        g0 = self.poses_g[k]
        g1 = self.poses_g[(k + 1) % len(self.poses_g)]
        axis, angle = _rotation_between(g0, g1)
        moving = tau > self.dwell_s
        frac = np.clip((tau - self.dwell_s) / max(self.move_s, 1e-9), 0.0, 1.0)
        phi = np.where(moving, frac * angle, 0.0)
        g = _rotate(g0, axis, phi)
        rate_rad = np.where(moving, angle / max(self.move_s, 1e-9), 0.0)
        # dg/dt = rate * (axis x g) = -omega x g  =>  omega = -rate * axis   (body frame)
        omega_dps = -np.degrees(rate_rad)[:, None] * axis
        return g, omega_dps, ~moving


def _rotation_between(g0: np.ndarray, g1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cross = np.cross(g0, g1)
    norm = np.linalg.norm(cross, axis=1)
    angle = np.arctan2(norm, np.einsum("ij,ij->i", g0, g1))
    # antipodal or identical poses: turn about any axis normal to g0
    fallback = np.cross(g0, np.where(np.abs(g0[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    axis = np.where(norm[:, None] > 1e-9, cross, fallback)
    axis = axis / np.linalg.norm(axis, axis=1)[:, None]
    return axis, angle


def _rotate(v: np.ndarray, axis: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Rodrigues' rotation of vectors v about unit axes by angles phi [rad], row-wise."""
    c, s = np.cos(phi)[:, None], np.sin(phi)[:, None]
    dot = np.einsum("ij,ij->i", axis, v)[:, None]
    return v * c + np.cross(axis, v) * s + axis * dot * (1 - c)


def tumble(dwell_s: float = 1.5, move_s: float = 0.5) -> Schedule:
    """The default 18-pose tumble: the 6 cube faces and 12 edges, ordered to avoid 180 deg flips."""
    e = _EDGE
    poses = [
        (0, 0, 1), (e, 0, e), (1, 0, 0), (e, e, 0), (0, 1, 0), (0, e, e),
        (0, -e, e), (0, -1, 0), (e, -e, 0), (e, 0, -e), (0, 0, -1), (-e, 0, -e),
        (-1, 0, 0), (-e, -e, 0), (0, -e, -e), (0, e, -e), (-e, e, 0), (-e, 0, e),
    ]
    return Schedule(np.asarray(poses, dtype=np.float64), dwell_s, move_s)


def still(gravity_g: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> Schedule:
    """One pose held forever (the unit sitting in its vehicle)."""
    g = np.asarray([gravity_g], dtype=np.float64)
    return Schedule(g / np.linalg.norm(g), 3600.0, 0.0)


def load_schedule(path: str | Path) -> Schedule:
    """Load a YAML schedule: ``{dwell_s: 2, move_s: 0.5, poses: [[0,0,1], [1,0,0], ...]}``."""
    name = str(path)
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{name}: cannot read the schedule ({err})") from err
    if not isinstance(doc, dict) or "poses" not in doc:
        raise ConfigError(f"{name}: field 'poses' missing; give a list of [gx, gy, gz] vectors in g")
    try:
        poses = np.asarray(doc["poses"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: field 'poses' must be a list of [gx, gy, gz] numbers") from None
    if poses.ndim != 2 or poses.shape[1] != 3 or len(poses) < 1:
        raise ConfigError(f"{name}: field 'poses' must be a list of [gx, gy, gz] vectors in g")
    norms = np.linalg.norm(poses, axis=1)
    if np.any(norms < 1e-6):
        raise ConfigError(f"{name}: field 'poses' holds a zero vector; each pose needs a direction")
    dwell, move = doc.get("dwell_s", 2.0), doc.get("move_s", 0.5)
    for field, value in (("dwell_s", dwell), ("move_s", move)):
        if not isinstance(value, int | float) or value < 0:
            raise ConfigError(f"{name}: field '{field}' must be a number of seconds >= 0")
    if dwell <= 0:
        raise ConfigError(f"{name}: field 'dwell_s' must be > 0 s so the unit rests at each pose")
    return Schedule(poses / norms[:, None], float(dwell), float(move))


class EarthFixed:
    """A vector fixed on the Earth (north, the Earth's rotation) [any unit] as the body of a unit on
    ``schedule`` sees it: it turns with every move exactly as gravity does. The vector at the start of
    each segment is carried from switch-on, so a tumble whose moves do not close (a net turn about the
    vertical per cycle) changes the unit's heading from cycle to cycle, as it would on a real fixture."""

    def __init__(self, schedule: Schedule, v0_body: np.ndarray) -> None:
        self.schedule = schedule
        self._starts = [np.asarray(v0_body, dtype=np.float64)]  # the vector at each segment's start

    def at(self, t_on_s: np.ndarray) -> np.ndarray:
        """The vector in the body frame (N, 3) at t_on [s]."""
        seg, axis, phi, _ = self.schedule.motion(t_on_s)
        n_pose = len(self.schedule.poses_g)
        g = self.schedule.poses_g
        while len(self._starts) <= int(seg.max(initial=0)):
            j = len(self._starts) - 1
            k = j % n_pose
            ax, ang = _rotation_between(g[k:k + 1], g[(k + 1) % n_pose:(k + 1) % n_pose + 1])
            self._starts.append(_rotate(self._starts[j][None, :], ax, ang)[0])
        return _rotate(np.asarray(self._starts)[seg], axis, phi)

