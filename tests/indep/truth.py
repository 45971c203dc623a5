"""The emulated unit's physical truth: its drift, its poses, its temperature and its noise.

Our own choices, not the daemon simulator's: the drift is a per-unit gravity-dependent part on the
seed-000 terms plus a bias that is drawn anew at every power cycle, optionally a temperature slope;
the pose schedule is random orientations held for a random 0.8-3 s, joined by constant-rate moves;
the temperature warms up as two exponentials with a slow ripple. Units: deg/s, g, degC, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tests.indep.wire import SEED000, evaluate_terms

GRADES = {
    # name: (white noise per sample [deg/s], gravity-term drift scale [deg/s], bias scale [deg/s])
    "fibre": (0.002, 0.004, 0.01),
    "mems": (0.1, 0.05, 0.2),
}


def _rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def _log_rotation(r: np.ndarray) -> tuple[np.ndarray, float]:
    """Axis and angle [rad] of rotation matrix r."""
    cos = np.clip((np.trace(r) - 1) / 2, -1.0, 1.0)
    angle = float(np.arccos(cos))
    if angle < 1e-9:
        return np.array([0.0, 0.0, 1.0]), 0.0
    if np.pi - angle < 1e-6:
        # near 180 deg: axis from the symmetric part
        m = (r + np.eye(3)) / 2
        axis = m[int(np.argmax(np.diag(m)))]
        return axis / np.linalg.norm(axis), angle
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2 * np.sin(angle))
    return axis, angle


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random orientation (body-to-level), from a random unit quaternion."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


@dataclass
class Truth:
    """Drift law of one unit: drift = G @ seed000_terms(g) + bias_session + k_T * (T - 25)."""

    gravity_coeffs: np.ndarray  # 3 x 10 on SEED000, with the constant column 0 (bias is separate)
    bias: np.ndarray            # 3, deg/s, redrawn at every power cycle
    temp_slope: np.ndarray      # 3, deg/s per degC around 25 degC
    noise_dps: float            # white gyro noise per sample [deg/s]
    accel_noise_g: float = 2e-4

    @staticmethod
    def for_unit(serial: int, grade: str, noise_dps: float | None, temp_slope_dps: float) -> Truth:
        noise, g_scale, _ = GRADES[grade]
        rng = np.random.default_rng(serial)
        coeffs = rng.uniform(-1.0, 1.0, size=(3, len(SEED000))) * g_scale
        coeffs[:, 0] = 0.0
        slope = rng.uniform(0.5, 1.0, size=3) * temp_slope_dps * rng.choice([-1.0, 1.0], size=3)
        return Truth(coeffs, np.zeros(3), slope, noise if noise_dps is None else noise_dps)

    def new_bias(self, grade: str, rng: np.random.Generator) -> None:
        """A turn-on bias: each power cycle gives a different one (the run-to-run repeatability)."""
        self.bias = rng.uniform(-1.0, 1.0, size=3) * GRADES[grade][2]

    def drift(self, g_unit: np.ndarray, temp: np.ndarray) -> np.ndarray:
        """True systematic drift (N x 3) [deg/s] for unit gravity vectors g_unit (N x 3)."""
        terms = evaluate_terms(SEED000, g_unit, temp, np.zeros(len(temp)), np.zeros(len(temp)))
        return terms @ self.gravity_coeffs.T + self.bias + np.outer(temp - 25.0, self.temp_slope)


class PoseSchedule:
    """Random orientations with random dwell (0.8-3 s), joined by constant-rate moves (0.3-0.6 s).

    The schedule is regenerated per session from the unit's seed and boot counter. ``poses`` is the
    list of held orientations: the status reports the drift RMS over their gravity directions.
    """

    def __init__(self, seed: int, n_poses: int = 24) -> None:
        rng = np.random.default_rng(seed)
        self.rotations = [random_rotation(rng) for _ in range(n_poses)]
        self.dwell = rng.uniform(0.8, 3.0, size=n_poses)
        self.move = rng.uniform(0.3, 0.6, size=n_poses)
        seg = []  # (t_start, kind, index)
        t = 0.0
        for i in range(n_poses):
            seg.append((t, "dwell", i))
            t += self.dwell[i]
            seg.append((t, "move", i))
            t += self.move[i]
        self.period = t
        self.starts = np.array([s[0] for s in seg])
        self.kinds = [s[1] for s in seg]
        self.index = [s[2] for s in seg]
        self.moves = []
        for i in range(n_poses):
            r0, r1 = self.rotations[i], self.rotations[(i + 1) % n_poses]
            axis, angle = _log_rotation(r0.T @ r1)  # body-frame rotation from pose i to i+1
            self.moves.append((axis, angle))

    def gravity_at_poses(self) -> np.ndarray:
        """Unit specific-force direction in body axes (N x 3) at each held pose (+z up reads +1)."""
        return np.array([r.T @ np.array([0.0, 0.0, 1.0]) for r in self.rotations])

    def state(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True body rate [deg/s] (N x 3) and specific force [g] (N x 3) at unit times t_s."""
        tp = np.mod(t_s, self.period)
        seg = np.searchsorted(self.starts, tp, side="right") - 1
        rate = np.zeros((len(t_s), 3))
        force = np.zeros((len(t_s), 3))
        up = np.array([0.0, 0.0, 1.0])
        for j, s in enumerate(seg):
            i = self.index[s]
            r = self.rotations[i]
            if self.kinds[s] == "dwell":
                force[j] = r.T @ up
                continue
            axis, angle = self.moves[i]
            frac = (tp[j] - self.starts[s]) / self.move[i]
            rt = r @ _rodrigues(axis, angle * frac)
            force[j] = rt.T @ up
            rate[j] = np.degrees(axis * angle / self.move[i])
        return rate, force


def temperature(t_s: np.ndarray, start_degc: float) -> np.ndarray:
    """Warm-up after switch-on: two exponentials (8 s and 60 s) and a 0.2 degC ripple of 40 s."""
    return (start_degc + 6.0 * (1 - np.exp(-t_s / 8.0)) + 4.0 * (1 - np.exp(-t_s / 60.0))
            + 0.2 * np.sin(2 * np.pi * t_s / 40.0))
