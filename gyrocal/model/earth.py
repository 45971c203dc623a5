"""Earth rotation as a strapdown gyro at rest sees it.

Why: a gyro at rest is not at rest in inertial space. It reads the Earth's rotation, 15.041 deg/h,
projected on its axes: Omega sin(latitude) along the local vertical and Omega cos(latitude) along
north. That is true rate, not drift. A calibrator that takes the rate at rest for drift learns it into
the unit's set, and the unit then removes the Earth's rotation from its own output. For a unit whose
drift is a few deg/h or less (tactical, fibre), that is the largest error the set can carry, and it
blinds a navigation system that aligns by gyrocompassing.

The vertical part needs only the latitude: at rest the accelerometers read the specific force, which
points up, so the vertical Earth rate in the body frame is Omega sin(latitude) a / |a|, whatever the
pose and heading. The horizontal part points north, which a unit that knows only gravity cannot tell.
"""

from __future__ import annotations

import numpy as np

OMEGA_IE_DPS = float(np.degrees(7.2921150e-5))
"""The Earth's rotation rate (WGS 84) [deg/s]: 0.0041781 deg/s, 15.041 deg/h."""


def vertical_earth_rate_dps(accel_g: np.ndarray, latitude_deg: float) -> np.ndarray:
    """The vertical part of the Earth rate [deg/s] (N, 3) in the body frame, from the measured
    specific force [g] (N, 3) at rest: Omega sin(latitude) a / |a|. Samples with no specific force
    (|a| = 0, NaN) get 0."""
    a = np.atleast_2d(np.asarray(accel_g, dtype=np.float64))
    norm = np.linalg.norm(a, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        up = np.where(norm > 0, a / norm, 0.0)
    return np.nan_to_num(up) * (OMEGA_IE_DPS * np.sin(np.radians(latitude_deg)))


def earth_rate_body_dps(up_body: np.ndarray, north_body: np.ndarray, latitude_deg: float) -> np.ndarray:
    """The whole Earth rate [deg/s] in the body frame, from the unit vectors up and north in it."""
    lat = np.radians(latitude_deg)
    return OMEGA_IE_DPS * (np.cos(lat) * np.asarray(north_body) + np.sin(lat) * np.asarray(up_body))


def horizontal_basis(up: np.ndarray) -> np.ndarray:
    """Two unit vectors (3, 2) spanning the plane normal to the unit vector ``up``: the body's x axis
    projected on it (y when x is near vertical), then up x that."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - up * float(ref @ up)
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(up, e1)])


def north_in_body(up_body: np.ndarray, heading_deg: float) -> np.ndarray:
    """North [unit vector] in the body frame of a unit whose up is ``up_body`` and whose x axis,
    projected on the horizontal, points ``heading_deg`` east of north (y when x is vertical)."""
    up = np.asarray(up_body, dtype=np.float64)
    basis = horizontal_basis(up / np.linalg.norm(up))
    psi = np.radians(heading_deg)
    return basis @ np.array([np.cos(psi), np.sin(psi)])
