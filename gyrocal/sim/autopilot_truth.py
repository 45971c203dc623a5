"""The offset error a virtual autopilot is left with, from its own truth: before and after a push.

Shared by ``gyrocal demo --mavlink`` and benchmarks/bench_mavlink.py, so both report the same figure:

    error(T) = true raw offset(T) - what the autopilot subtracts at T with its parameters   [deg/h]

"before" uses the parameters the autopilot left the factory with (seed ``seed``), "after" those it
holds at the end, both at the learning boot's switch-on bias (boot 1, or the last boot of a run
with several). The subtraction is evaluated
continuously (gyrocal.mavlink.profiles: ``applied`` + ``clamp_adjust``, clamped to TMIN..TMAX); PX4's
1 degC staircase adds at most slope x 1 degC on top (``px4_staircase_dph``). For a PX4 whose
TC_G_ENABLE was 0 at boot the set applies after the next reboot, under a new switch-on bias that adds
a constant; ``shape_after_dph`` (the error minus its mean over the range) is the part a reboot keeps.

Frames: the error is worked out in the autopilot's SENSOR frame (its raw offset and its subtraction,
with the profile's formulas at board rotation 0, i.e. unrotated) and rotated into the BODY frame by
the virtual autopilot's own rotation (gyrocal/sim/board_rotation.py), not by the link's
gyrocal/mavlink/rotation.py: a wrong transform in the link shows here as a wrong calibration. The
figures are per body axis, the axes the IMU messages and the daemon use.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gyrocal.mavlink.poly import evaluate
from gyrocal.mavlink.profiles import PROFILES
from gyrocal.sim import board_rotation
from gyrocal.sim.autopilot import VirtualAutopilot

DPH = 3600.0


def held_range(kind: str, params: dict[str, float]) -> tuple[float, float]:
    """TMIN, TMAX [degC] of the set the autopilot holds (IMU 0)."""
    prof = PROFILES[kind](0)
    return float(params[prof.p_tmin]), float(params[prof.p_tmax])  # type: ignore[attr-defined]


def offset_errors(kind: str, seed: int, final_params: dict[str, float], temps: np.ndarray,
                  boot: int = 1, ambients_c: tuple[float, ...] = ()) -> dict[str, Any]:
    """Before/after offset error [deg/h] (N, 3) at ``temps`` [degC] for the learning boot ``boot``
    (the last of a run; ``ambients_c`` as the run's ``--ambient``: each boot's own boot calibration)."""
    ap = VirtualAutopilot(kind, 250, seed, ambients_c=ambients_c)
    for _ in range(boot):
        ap.power_on()
    before_params = dict(ap.params)
    prof = PROFILES[kind](0)
    raw = ap.raw_offset_dps(temps)  # sensor frame
    rot = int(final_params.get(ap.rotation_param, 0.0))
    unrotated = {n: 0.0 for n in prof.rotation_names(final_params)}

    def error(p: dict[str, float]) -> np.ndarray:
        p = {**p, **unrotated}  # the profile's subtraction in the sensor frame
        err_sensor = raw - (evaluate(prof.applied(p), temps) + prof.clamp_adjust(p, temps))
        return board_rotation.rotate(rot, err_sensor)  # the virtual autopilot's own rotation to body

    after_params = {**before_params, **{k: float(v) for k, v in final_params.items() if k in before_params}}
    if kind == "ardupilot":  # the learning boot's own gyro calibration, not the one saved at the last boot
        for k in ("INS_GYROFFS_X", "INS_GYROFFS_Y", "INS_GYROFFS_Z", "INS_GYR1_CALTEMP"):
            after_params[k] = (
                final_params[k] if final_params.get("INS_TCAL1_ENABLE") == 1 else before_params[k]
            )
    b, a = error(before_params) * DPH, error(after_params) * DPH
    out: dict[str, Any] = {
        "temps_c": temps.round(2).tolist(),
        "before_dph": b.round(1).tolist(),
        "after_dph": a.round(1).tolist(),
        "shape_after_dph": (a - a.mean(axis=0)).round(1).tolist(),
    }
    out["improvement_x"] = (
        (np.max(np.abs(b), axis=0) / np.maximum(np.max(np.abs(a), axis=0), 1e-9)).round(1).tolist()
    )
    out["board_rotation"] = rot
    if kind == "px4":
        slope = np.abs(np.gradient(board_rotation.rotate(rot, raw), temps, axis=0)).max(axis=0)
        out["px4_staircase_dph"] = (slope * 1.0 * DPH).round(1).tolist()
    return out
