"""The autopilot parameter semantics, checked against the autopilots' own formulas re-typed here.

The reference evaluations below are written from the cited sources, not from gyrocal.mavlink:
PX4 TemperatureCompensation::calc_thermal_offsets_3D + Gyroscope::Correct, and ArduPilot
AP_InertialSensor_TCal::correct_sensor + AP_InertialSensor_Backend::_rotate_and_correct_gyro.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from gyrocal.mavlink.poly import evaluate, shift  # noqa: E402
from gyrocal.mavlink.profiles import INT8, INT32, REAL32, ArduPilot, Px4, decode_param, encode_param  # noqa: E402

RAD = np.pi / 180.0
Q = np.array([[0.05, 1e-3, -2e-5, 3e-7], [-0.02, -5e-4, 1e-5, 0.0], [0.01, 2e-4, 0.0, -1e-7]])


def px4_output_rad(p: dict[str, float], raw_rad: np.ndarray, temp: float) -> np.ndarray:
    """PX4: corrected = raw - thermal_offset(T) - CAL_GYRO0_OFF, thermal only when enabled and ids match."""
    thermal = np.zeros(3)
    if p["TC_G_ENABLE"] == 1 and p["TC_G0_ID"] == p["CAL_GYRO0_ID"]:
        t = min(max(temp, p["TC_G0_TMIN"]), p["TC_G0_TMAX"])
        d = t - p["TC_G0_TREF"]
        thermal = np.array(
            [
                p[f"TC_G0_X0_{i}"]
                + p[f"TC_G0_X1_{i}"] * d
                + p[f"TC_G0_X2_{i}"] * d * d
                + p[f"TC_G0_X3_{i}"] * d**3
                for i in range(3)
            ]
        )
    return raw_rad - thermal - np.array([p[f"CAL_GYRO0_{a}OFF"] for a in "XYZ"])


def ardupilot_output_rad(p: dict[str, float], raw_rad: np.ndarray, temp: float) -> np.ndarray:
    """ArduPilot: v -= P(T-35) - P(Tcal-35) (T, Tcal clamped; P without constant, x1e-6); v -= offsets."""
    v = raw_rad.copy()
    if p["INS_TCAL1_ENABLE"] == 1:
        lo, hi = p["INS_TCAL1_TMIN"], p["INS_TCAL1_TMAX"]

        def poly(x: float) -> np.ndarray:
            c = [np.array([p[f"INS_TCAL1_GYR{k}_{a}"] for a in "XYZ"]) for k in (1, 2, 3)]
            return (c[0] + (c[1] + c[2] * x) * x) * x * 1e-6

        v = v - poly(min(max(temp, lo), hi) - 35.0) + poly(min(max(p["INS_GYR1_CALTEMP"], lo), hi) - 35.0)
    return v - np.array([p[f"INS_GYROFFS_{a}"] for a in "XYZ"])


@pytest.mark.parametrize("caltemp", [22.3, -300.0, 60.0])
def test_ardupilot_parameters_subtract_exactly_our_polynomial(caltemp: float) -> None:
    prof = ArduPilot(0)
    ctx = {"INS_GYR1_CALTEMP": caltemp}
    p = {**ctx, **prof.to_params(Q, ctx, 20.0, 50.0), "INS_TCAL1_ENABLE": 1.0}
    raw = np.array([0.3, -0.2, 0.1]) * RAD
    for temp in (20.0, 27.5, 41.0, 50.0):
        out = ardupilot_output_rad(p, raw + evaluate(Q, np.array([temp]))[0] * RAD, temp)
        assert np.allclose(out / RAD, raw / RAD, atol=2e-6)  # float32 parameters: < 0.01 deg/h
    assert np.allclose(evaluate(prof.applied(p), np.array([33.0])), evaluate(Q, np.array([33.0])), atol=2e-6)


def test_px4_parameters_subtract_exactly_our_polynomial_with_its_cal_offset() -> None:
    prof = Px4(0)
    ctx = {
        "CAL_GYRO0_ID": 2490378.0,
        "CAL_GYRO0_XOFF": 0.001,
        "CAL_GYRO0_YOFF": -0.003,
        "CAL_GYRO0_ZOFF": 0.0,
    }
    p = {**ctx, **prof.to_params(Q, ctx, 20.0, 50.0), "TC_G_ENABLE": 1.0}
    assert p["TC_G0_ID"] == 2490378.0 and p["TC_G0_TMIN"] == 20.0 and p["TC_G0_TMAX"] == 50.0
    raw = np.array([0.3, -0.2, 0.1]) * RAD
    for temp in (20.0, 33.3, 50.0):
        out = px4_output_rad(p, raw + evaluate(Q, np.array([temp]))[0] * RAD, temp)
        assert np.allclose(out / RAD, raw / RAD, atol=2e-6)


@pytest.mark.parametrize("prof", [Px4(0), ArduPilot(0)], ids=["px4", "ardupilot"])
def test_outside_the_range_the_autopilot_clamps_and_clamp_adjust_says_by_how_much(prof) -> None:
    ctx = {
        "CAL_GYRO0_ID": 7.0,
        "INS_GYR1_CALTEMP": 30.0,
        "CAL_GYRO0_XOFF": 1e-3,
        "CAL_GYRO0_YOFF": 0.0,
        "CAL_GYRO0_ZOFF": -2e-3,
    }
    p = {**ctx, **prof.to_params(Q, ctx, 25.0, 45.0), prof.enable.name: 1.0}
    raw = np.zeros(3)
    ref = px4_output_rad if prof.name == "px4" else ardupilot_output_rad
    for temp in (10.0, 30.0, 60.0):
        subtracted = -ref(p, raw, temp) / RAD
        predicted = evaluate(prof.applied(p), np.array([temp]))[0] + prof.clamp_adjust(p, np.array([temp]))[0]
        assert np.allclose(subtracted, predicted, atol=2e-6)
    assert np.allclose(prof.clamp_adjust(p, np.array([30.0])), 0.0)


def test_disabled_compensation_reports_only_the_plain_offset() -> None:
    prof = ArduPilot(0)
    p = {
        **prof.to_params(Q, {"INS_GYR1_CALTEMP": 30.0}, 20, 50),
        "INS_TCAL1_ENABLE": 0.0,
        "INS_GYR1_CALTEMP": 30.0,
    }
    q = prof.applied(p)
    assert np.all(q[:, 1:] == 0)
    assert np.allclose(q[:, 0], [p[f"INS_GYROFFS_{a}"] / RAD for a in "XYZ"])


def test_shift_is_exact_and_invertible() -> None:
    a = shift(Q, 35.0)
    x = np.array([-10.0, 0.0, 17.0, 80.0])
    assert np.allclose(evaluate(a, x - 35.0), evaluate(Q, x), rtol=1e-12, atol=1e-15)
    assert np.allclose(shift(a, -35.0), Q, rtol=1e-12, atol=1e-18)


def test_param_encodings_px4_bytewise_and_ardupilot_cast() -> None:
    dev_id = 2490378  # a 22-bit device id: a float cast would still hold it, 2**25 + 1 would not
    for v in (dev_id, 2**25 + 1, -5):
        assert decode_param(encode_param(v, INT32, True), INT32, True) == v
    assert encode_param(1, INT8, False) == 1.0 and decode_param(1.0, INT8, False) == 1.0
    assert decode_param(encode_param(0.1, REAL32, True), REAL32, True) == float(np.float32(0.1))


def test_range_check_refuses_an_absurd_offset() -> None:
    assert Px4(0).check_range(Q * 1000, 20, 50) is not None
    assert Px4(0).check_range(Q, 20, 50) is None
    assert "NaN" in (ArduPilot(0).check_range(Q * np.nan, 20, 50) or "")
