"""Board rotations: the tables (gyrocal/mavlink/rotation.py), the profiles' sensor-frame coefficients,
and a push that meets a rotation changed under it."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from gyrocal.mavlink.paramtx import ParamPush, ParamRead, ParamReadAll  # noqa: E402
from gyrocal.mavlink.poly import DEG_PER_RAD, evaluate  # noqa: E402
from gyrocal.mavlink.profiles import REAL32, ArduPilot, Px4  # noqa: E402
from gyrocal.mavlink.rotation import (  # noqa: E402
    ARDUPILOT_EULER_DEG,
    PX4_EULER_DEG,
    RotationError,
    ardupilot_board_matrix,
    px4_board_matrix,
)
from gyrocal.sim import board_rotation  # noqa: E402
from tests.test_mavlink_paramtx import Server  # noqa: E402

Q = np.array([[0.05, 1e-3, -2e-5, 3e-7], [-0.02, -5e-4, 1e-5, 0.0], [0.01, 2e-4, 0.0, -1e-7]])
S = np.sqrt(0.5)

# hand-derived: column j is where the board's axis j points in the body frame (body = R @ board)
HAND = {
    1: [[S, -S, 0], [S, S, 0], [0, 0, 1]],  # YAW_45
    2: [[0, -1, 0], [1, 0, 0], [0, 0, 1]],  # YAW_90: board x -> body y, board y -> body -x
    4: [[-1, 0, 0], [0, -1, 0], [0, 0, 1]],  # YAW_180
    6: [[0, 1, 0], [-1, 0, 0], [0, 0, 1]],  # YAW_270
    8: [[1, 0, 0], [0, -1, 0], [0, 0, -1]],  # ROLL_180: upside down
    10: [[0, 1, 0], [1, 0, 0], [0, 0, -1]],  # ROLL_180_YAW_90
    12: [[-1, 0, 0], [0, 1, 0], [0, 0, -1]],  # PITCH_180
    16: [[1, 0, 0], [0, 0, -1], [0, 1, 0]],  # ROLL_90: board y -> body z
    24: [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],  # PITCH_90: board x -> body -z (nose up)
}


@pytest.mark.parametrize("rot", sorted(HAND))
def test_entries_match_hand_derived_matrices(rot: int) -> None:
    assert np.allclose(px4_board_matrix(rot), HAND[rot], atol=1e-15)
    assert np.allclose(ardupilot_board_matrix(rot), HAND[rot], atol=1e-15)


def test_every_entry_is_a_proper_rotation() -> None:
    mats = [px4_board_matrix(i) for i in range(len(PX4_EULER_DEG))]
    mats += [ardupilot_board_matrix(i) for i in range(len(ARDUPILOT_EULER_DEG))]
    mats += [ardupilot_board_matrix(101, (10.0, -20.0, 225.0)), px4_board_matrix(2, (1.5, -2.0, 0.5))]
    for m in mats:
        assert np.allclose(m @ m.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(m), 1.0, atol=1e-12)


def test_the_tables_agree_with_the_component_swaps_of_ardupilot_vector3_rotate() -> None:
    """Two definitions in the sources (Euler angles vs. ArduPilot's explicit swaps) give one matrix."""
    for rot in board_rotation.SUPPORTED:
        swaps = board_rotation.rotate(rot, np.eye(3)).T  # columns: the images of the unit vectors
        assert np.allclose(swaps, px4_board_matrix(rot), atol=1e-12), rot
        assert np.allclose(swaps, ardupilot_board_matrix(rot), atol=1e-12), rot


def test_values_that_cannot_be_mapped_are_refused_with_the_parameter_and_why() -> None:
    with pytest.raises(RotationError, match="SENS_BOARD_ROT = 48"):
        px4_board_matrix(48)
    with pytest.raises(RotationError, match="AHRS_ORIENTATION = 100 .*AHRS_CUSTOM_ROLL"):
        ardupilot_board_matrix(100)
    with pytest.raises(RotationError, match="AHRS_ORIENTATION = 44"):
        ardupilot_board_matrix(44)
    why = ArduPilot(0).problem({"AHRS_ORIENTATION": 101.0})
    assert why and "CUST_ROT1_ROLL" in why and "sensor frame" in why
    assert Px4(0).problem({"SENS_BOARD_ROT": 2.0, "CAL_GYRO0_ID": 7.0}) is None


def _px4_ctx(rot: float, level=(0.0, 0.0, 0.0)) -> dict[str, float]:
    return {"CAL_GYRO0_ID": 7.0, "TC_G_ENABLE": 1.0, "SENS_BOARD_ROT": rot,
            **dict(zip(Px4.P_LEVEL, level, strict=True)), "CAL_GYRO0_XOFF": 0.001}


def test_px4_yaw_90_writes_the_body_polynomial_in_the_sensor_frame() -> None:
    prof = Px4(0)
    ctx = _px4_ctx(2.0)
    params = {**ctx, **prof.to_params(Q, ctx, 20.0, 50.0)}
    # body = Rz(90) sensor: body x = -sensor y, body y = sensor x  =>  sensor x = body y, sensor y = -body x
    assert np.isclose(params["TC_G0_X3_0"], Q[1, 3] / DEG_PER_RAD, rtol=1e-6)
    assert np.isclose(params["TC_G0_X3_1"], -Q[0, 3] / DEG_PER_RAD, rtol=1e-6)
    assert np.isclose(params["TC_G0_X3_2"], Q[2, 3] / DEG_PER_RAD, rtol=1e-6)
    assert np.allclose(prof.applied(params), Q, atol=1e-9)  # what it subtracts, seen in the body frame


@pytest.mark.parametrize(
    "prof,ctx",
    [
        (Px4(0), _px4_ctx(8.0)),
        (Px4(0), _px4_ctx(14.0, (1.5, -2.0, 3.0))),
        (ArduPilot(0), {"AHRS_ORIENTATION": 2.0, "INS_GYR1_CALTEMP": 27.0}),
        (ArduPilot(0), {"AHRS_ORIENTATION": 8.0, "INS_GYR1_CALTEMP": 27.0}),
        (ArduPilot(0), {"AHRS_ORIENTATION": 101.0, "CUST_ROT1_ROLL": 180.0, "CUST_ROT1_PITCH": 0.0,
                        "CUST_ROT1_YAW": 225.0, "INS_GYR1_CALTEMP": 27.0}),
    ],
    ids=["px4-roll180", "px4-roll180yaw270-level", "ap-yaw90", "ap-roll180", "ap-custom1"],
)
def test_a_rotated_autopilot_subtracts_exactly_our_body_frame_polynomial(prof, ctx) -> None:
    params = {**ctx, **prof.to_params(Q, ctx, 20.0, 50.0), prof.enable.name: 1.0}
    r = prof.board_matrix(params)
    temps = np.linspace(20.0, 50.0, 7)
    # the autopilot's own sum in the sensor frame (profile formulas at rotation 0), then rotated by R
    unrot = {**params, **{n: 0.0 for n in prof.rotation_names(params)}}
    sensor = evaluate(prof.applied(unrot), temps)
    assert np.allclose(sensor @ r.T, evaluate(Q, temps), atol=2e-7)
    assert np.allclose(evaluate(prof.applied(params), temps), evaluate(Q, temps), atol=2e-7)
    # outside the range, clamp_adjust is the clamped difference, rotated alike
    hot = np.array([60.0])
    clamped = evaluate(Q, np.array([50.0])) - evaluate(Q, hot)
    assert np.allclose(prof.clamp_adjust(params, hot), clamped, atol=2e-7)


class RotServer(Server):
    """The paramtx test server plus ArduPilot's custom-rotation parameters, and a ground station that
    changes the board rotation after the ``change_after``-th PARAM_SET."""

    def __init__(self, profile, initial, extra: dict[str, float] | None = None) -> None:
        super().__init__(profile, initial)
        for k, v in (extra or {}).items():
            self.p[k], self.types[k] = v, REAL32
        self.change_after: int | None = None
        self.change: tuple[str, float] = ("", 0.0)

    def send(self, req: object) -> None:
        if isinstance(req, ParamRead) and req.name not in self.p:
            return  # a parameter this firmware does not have: no PARAM_VALUE ever comes
        super().send(req)
        if self.change_after is not None and len(self.sets) >= self.change_after:
            self.p[self.change[0]] = self.change[1]
            self.change_after = None


def test_a_custom_rotation_is_read_and_used_for_the_push() -> None:
    prof = ArduPilot(0)
    cust = {"CUST_ROT1_ROLL": 0.0, "CUST_ROT1_PITCH": 0.0, "CUST_ROT1_YAW": 90.0}
    srv = RotServer(prof, {"AHRS_ORIENTATION": 101.0, "INS_GYR1_CALTEMP": 30.0}, cust)
    push = ParamPush(prof, Q, 20.0, 50.0, srv.send, 0.0)
    srv.pump(push)
    assert push.finished and push.outcome.ok, push.outcome
    assert push.rotation == {"AHRS_ORIENTATION": 101.0, **cust}
    assert np.allclose(prof.applied(srv.p), Q, atol=1e-7)
    # yaw 90 as a custom rotation gives the same parameters as enum 2
    ctx2 = {"AHRS_ORIENTATION": 2.0, "INS_GYR1_CALTEMP": 30.0}
    assert prof.to_params(Q, ctx2, 20.0, 50.0) == push.target
    rd = ParamReadAll(prof, srv.send, 0.0)
    srv.pump(rd)
    assert rd.finished and not rd.error and rd.values["CUST_ROT1_YAW"] == 90.0


@pytest.mark.parametrize("when", ["before_enable", "after_enable"])
def test_a_rotation_changed_during_the_push_never_leaves_the_set_active(when: str) -> None:
    prof = Px4(0)
    srv = RotServer(prof, {"CAL_GYRO0_ID": 42.0, "TC_G_ENABLE": 1.0, "SENS_BOARD_ROT": 2.0})
    n_sets = 1 + len(prof.to_params(Q, _px4_ctx(2.0), 20.0, 50.0))  # ENABLE=0 and every coefficient
    srv.change_after = n_sets if when == "before_enable" else n_sets + 1  # + the ENABLE=1 write
    srv.change = ("SENS_BOARD_ROT", 4.0)
    push = ParamPush(prof, Q, 20.0, 50.0, srv.send, 0.0)
    srv.pump(push)
    assert push.finished and not push.outcome.ok
    assert "board rotation changed" in push.outcome.reason
    assert srv.p["TC_G_ENABLE"] == 0.0  # written for yaw 90, never left active under yaw 180
    if when == "before_enable":
        assert srv.sets.count("TC_G_ENABLE") == 1  # never enabled at all


def test_a_rotation_changed_to_an_unreadable_custom_one_leaves_compensation_off() -> None:
    """AHRS_ORIENTATION turns to 101 mid-push while CUST_ROT1_* do not exist (CUST_ROT_ENABLE = 0): the
    verify read cannot finish; the old set (for the old frame) is not restored, compensation stays off."""
    prof = ArduPilot(0)
    srv = RotServer(prof, {"INS_TCAL1_ENABLE": 1.0, "INS_GYR1_CALTEMP": 30.0, "INS_TCAL1_GYR1_X": 5.0})
    n_sets = 1 + len(prof.to_params(Q, {"INS_GYR1_CALTEMP": 30.0}, 20.0, 50.0))
    srv.change_after, srv.change = n_sets, ("AHRS_ORIENTATION", 101.0)
    push = ParamPush(prof, Q, 20.0, 50.0, srv.send, 0.0, timeout_s=0.5, retries=2)
    t = 0.0
    while not push.finished and t < 30.0:
        srv.pump(push)
        t += 0.6
        push.tick(t)
    assert push.finished and not push.outcome.ok
    assert "board rotation changed" in push.outcome.reason
    assert srv.p["INS_TCAL1_ENABLE"] == 0.0 and srv.p["INS_TCAL1_GYR1_X"] != 5.0  # off, old set not back


def test_a_remounted_board_does_not_warm_start_from_a_set_learnt_in_the_old_frame() -> None:
    from types import SimpleNamespace

    from gyrocal.daemon.capabilities import UnitCapabilities, frame_changed

    caps = UnitCapabilities("mavlink ardupilot", board_rotation={"AHRS_ORIENTATION": 8.0})
    same = SimpleNamespace(version=4, push={"status": "acked", "board_rotation": {"AHRS_ORIENTATION": 8.0}})
    other = SimpleNamespace(version=5, push={"status": "acked", "board_rotation": {"AHRS_ORIENTATION": 0.0}})
    older = SimpleNamespace(version=3, push={"status": "acked"})  # recorded before rotations were
    assert frame_changed(caps, same) is None and frame_changed(caps, older) is None
    assert frame_changed(caps, None) is None
    why = frame_changed(caps, other)
    assert why and "v5" in why and "AHRS_ORIENTATION" in why
    assert frame_changed(UnitCapabilities(), other) is None  # our protocol's unit: no board rotation
