"""The parameter push as pure logic, against a tiny in-test parameter server with injected faults."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from gyrocal.mavlink.paramtx import ParamPush, ParamRead, ParamReadAll, ParamSet  # noqa: E402
from gyrocal.mavlink.profiles import ArduPilot, Px4, decode_param, encode_param  # noqa: E402
from gyrocal.protocol.messages import NakReason  # noqa: E402

Q = np.array([[0.05, 1e-3, -2e-5, 3e-7], [-0.02, -5e-4, 1e-5, 0.0], [0.01, 2e-4, 0.0, -1e-7]])


class Server:
    """Holds parameters; answers a PARAM_SET with its echo and a read with its value, minus faults."""

    def __init__(self, profile, initial: dict[str, float]) -> None:
        self.profile = profile
        self.p = {x.name: 0.0 for x in profile.all_params()} | initial
        self.types = profile.types()
        for q in profile.extra_context(self.p):  # a PX4 1.12+: its gyro internal (CAL_GYRO0_ROT -1)
            if q.name in profile.optional:
                self.p.setdefault(q.name, -1.0)
                self.types[q.name] = q.ptype
        self.inbox: list[object] = []
        self.drop_next = 0
        self.clamp: str | None = None
        self.sets: list[str] = []
        self.partial_while_enabled = False

    def send(self, req: object) -> None:
        self.inbox.append(req)

    def pump(self, push, limit: int | None = None) -> None:
        """Deliver requests and answers until quiet (or ``limit`` requests)."""
        n = 0
        while self.inbox and (limit is None or n < limit):
            n += 1
            req = self.inbox.pop(0)
            if isinstance(req, ParamSet):
                v = decode_param(req.wire, req.ptype, self.profile.bytewise)
                if req.name == self.clamp:
                    v = 0.0
                self.p[req.name] = v
                self.sets.append(req.name)
                self._check_atomic(push)
                if self.drop_next:
                    self.drop_next -= 1
                    continue
            elif not isinstance(req, ParamRead):
                continue
            name = req.name
            push.on_value(
                name,
                encode_param(self.p[name], self.types[name], self.profile.bytewise),
                self.types[name],
                0.0,
            )

    def _check_atomic(self, push) -> None:
        """With compensation enabled, the coefficients must be all old or all new."""
        if self.p[self.profile.enable.name] != 1.0 or not push.target:
            return
        coeffs = list(push.target)
        new = [self.p[k] == push.target[k] for k in coeffs]
        old = [self.p[k] == push.before.get(k, 0.0) for k in coeffs]
        if not (all(new) or all(old)):
            self.partial_while_enabled = True


@pytest.mark.parametrize("profile", [Px4(0), ArduPilot(0)], ids=["px4", "ardupilot"])
def test_push_disables_writes_verifies_enables_and_reads_back(profile) -> None:
    srv = Server(profile, {"CAL_GYRO0_ID": 42.0, profile.enable.name: 1.0, "INS_GYR1_CALTEMP": 30.0})
    push = ParamPush(profile, Q, 20.0, 50.0, srv.send, 0.0)
    srv.pump(push)
    assert push.finished and push.outcome.ok, push.outcome
    assert srv.sets[0] == profile.enable.name and srv.sets[-1] == profile.enable.name
    assert srv.p[profile.enable.name] == 1.0
    assert all(srv.p[k] == v for k, v in push.target.items())
    assert not srv.partial_while_enabled


def test_a_lost_echo_is_asked_again_and_the_push_completes() -> None:
    profile = ArduPilot(0)
    srv = Server(profile, {"INS_GYR1_CALTEMP": 30.0})
    push = ParamPush(profile, Q, 20.0, 50.0, srv.send, 0.0, timeout_s=0.5, retries=3)
    srv.pump(push, limit=len(profile.all_params()) + 1)  # the context read and ENABLE=0
    srv.drop_next = 2
    # drive: the server drops two echoes; each timeout resends the same PARAM_SET
    t = 0.0
    while not push.finished and t < 60:
        srv.pump(push)
        t += 0.6
        push.tick(t)
    assert push.outcome.ok
    assert push.io.resends >= 1


def test_a_rejected_value_restores_the_old_set_and_naks() -> None:
    profile = Px4(0)
    before = {"CAL_GYRO0_ID": 42.0, "TC_G_ENABLE": 1.0, "TC_G0_ID": 42.0, "TC_G0_X1_0": 1e-5}
    srv = Server(profile, before)
    srv.clamp = "TC_G0_X2_1"
    push = ParamPush(profile, Q, 20.0, 50.0, srv.send, 0.0)
    srv.pump(push)
    out = push.outcome
    assert out is not None and not out.ok and out.nak == NakReason.OUT_OF_RANGE
    assert "rejected" in out.reason and out.restored
    assert srv.p["TC_G0_X1_0"] == np.float32(1e-5) and srv.p["TC_G_ENABLE"] == 1.0  # the old set, enabled
    assert not srv.partial_while_enabled


def test_silence_after_disable_leaves_compensation_off_never_partial() -> None:
    profile = ArduPilot(0)
    srv = Server(profile, {"INS_TCAL1_ENABLE": 1.0, "INS_GYR1_CALTEMP": 30.0})
    push = ParamPush(profile, Q, 20.0, 50.0, srv.send, 0.0, timeout_s=0.5, retries=2)
    srv.pump(push, limit=len(profile.all_params()) + 3)  # context, ENABLE=0, two writes: then silence
    srv.inbox.clear()
    t = 0.0
    while not push.finished and t < 60:
        t += 0.6
        push.tick(t)
        srv.inbox.clear()  # the autopilot is gone: nothing arrives
    out = push.outcome
    assert out is not None and not out.ok and not out.restored and "no PARAM_VALUE" in out.reason
    assert srv.p["INS_TCAL1_ENABLE"] == 0.0  # off, not a half-written set


def test_a_reboot_mid_push_aborts_with_a_clear_reason() -> None:
    profile = ArduPilot(0)
    srv = Server(profile, {"INS_TCAL1_ENABLE": 1.0, "INS_GYR1_CALTEMP": 30.0})
    push = ParamPush(profile, Q, 20.0, 50.0, srv.send, 0.0)
    srv.pump(push, limit=len(profile.all_params()) + 5)
    push.abort("the autopilot rebooted (boot time went back)")
    assert push.finished and not push.outcome.ok and "rebooted" in push.outcome.reason
    assert push.outcome.nak == NakReason.BUSY
    assert srv.p["INS_TCAL1_ENABLE"] == 0.0 and not srv.partial_while_enabled


def test_the_boot_gate_holds_each_request_until_the_clock_is_seen_and_the_ack_too() -> None:
    """A request (first or resent) leaves only when the gate says the autopilot's clock ran on since
    its last answer; a whole set read back is acked only after that too. A gate shut for longer than
    hold_max_s ends the push BUSY with the reason, never acked (an autopilot that rebooted in the
    last exchange took the rest of a PX4 set into a boot that applies none of it)."""
    profile = Px4(0)
    srv = Server(profile, {"CAL_GYRO0_ID": 42.0, "TC_G_ENABLE": 1.0})
    open_ = {"v": True}
    push = ParamPush(profile, Q, 20.0, 50.0, srv.send, 0.0, gate=lambda now: open_["v"], hold_max_s=5.0)
    srv.pump(push, limit=len(profile.all_params()) + 3)  # context read, DISABLE, two writes
    open_["v"] = False
    srv.pump(push)  # the answer to the request in flight: nothing more leaves
    assert not srv.inbox and push.phase.value == "write"
    push.tick(3.0)  # the request's timeout passes while held: nothing is resent either
    assert not srv.inbox and not push.finished
    open_["v"] = True
    push.tick(3.1)
    assert srv.inbox  # the held request goes
    srv.pump(push)
    assert push.finished and push.outcome.ok
    # everything written and read back, the clock not seen after the last answer: the ack waits
    srv2 = Server(profile, {"CAL_GYRO0_ID": 42.0, "TC_G_ENABLE": 1.0})
    ref: dict[str, ParamPush] = {}
    late = ref["p"] = ParamPush(profile, Q, 20.0, 50.0, srv2.send, 0.0,
                                gate=lambda now: "p" not in ref or ref["p"].phase.value != "confirm")
    srv2.pump(late)
    assert not late.finished and late.phase.value == "confirm" and all(
        srv2.p[k] == v for k, v in late.target.items()
    )
    late.tick(6.0)
    assert late.finished and not late.outcome.ok and late.outcome.nak == NakReason.BUSY
    assert "cannot be told" in late.outcome.reason


def test_a_rotation_other_than_the_hello_s_refuses_the_push_before_any_write() -> None:
    """The set was learnt under the rotation the link saw at HELLO; read otherwise in the context, the
    push writes nothing (a resend of a set learnt in the old frame was written in the new one and
    acked: 336-1904 deg/h left, an integrator's audit)."""
    profile = ArduPilot(0)
    srv = Server(profile, {"INS_TCAL1_ENABLE": 1.0, "INS_GYR1_CALTEMP": 30.0, "AHRS_ORIENTATION": 8.0})
    push = ParamPush(profile, Q, 20.0, 50.0, srv.send, 0.0, expect_rotation={"AHRS_ORIENTATION": 0.0})
    srv.pump(push)
    assert push.finished and not push.outcome.ok and push.outcome.nak == NakReason.BUSY
    assert "board rotation changed" in push.outcome.reason and not srv.sets


def test_a_late_echo_answering_the_final_read_is_read_again_not_a_failure() -> None:
    """PARAM_VALUE carries no request id: the DISABLE echo that came 1-2 s late answered the final
    read of ENABLE with 0, and the push failed (a spurious CRC mismatch before the retry acked: an
    audit). The final read-back is read once more before the set is called different."""
    profile = ArduPilot(0)
    srv = Server(profile, {"INS_TCAL1_ENABLE": 1.0, "INS_GYR1_CALTEMP": 30.0})
    push = ParamPush(profile, Q, 20.0, 50.0, srv.send, 0.0)
    stale = {"left": 1}
    real_pump = srv.pump

    def pump(push, limit=None):  # noqa: ANN001, ANN202
        while srv.inbox:
            req = srv.inbox[0]
            if (isinstance(req, ParamRead) and req.name == "INS_TCAL1_ENABLE" and stale["left"]
                    and srv.sets.count("INS_TCAL1_ENABLE") == 2):
                srv.inbox.pop(0)
                stale["left"] -= 1
                ptype = srv.types[req.name]
                push.on_value(req.name, encode_param(0.0, ptype, False), ptype, 0.0)
                continue
            real_pump(push, limit=1)

    pump(push)
    assert push.finished and push.outcome.ok and stale["left"] == 0


def test_an_unknown_parameter_fails_with_a_clear_error() -> None:
    profile = ArduPilot(0)
    srv = Server(profile, {})
    del srv.p["INS_TCAL1_GYR3_Z"]  # firmware without temperature calibration
    reader = ParamReadAll(profile, srv.send, 0.0, timeout_s=0.5, retries=2)
    t = 0.0
    while not reader.finished and t < 30:
        while srv.inbox:
            req = srv.inbox.pop(0)
            if req.name in srv.p:
                reader.on_value(
                    req.name,
                    encode_param(srv.p[req.name], srv.types[req.name], False),
                    srv.types[req.name],
                    t,
                )
        t += 0.6
        reader.tick(t)
    assert (
        reader.error is not None
        and "INS_TCAL1_GYR3_Z" in reader.error
        and "lacks the parameter" in reader.error
    )


def test_an_optional_parameter_this_firmware_lacks_is_taken_as_absent_not_a_fault() -> None:
    """CAL_GYROn_ROT exists from PX4 1.12: an older firmware does not answer it. The read goes on
    without it, and later reads do not ask again."""
    from gyrocal.mavlink.paramtx import OpRunner
    from gyrocal.mavlink.profiles import Px4

    prof = Px4(0)
    sent: list[object] = []
    io = OpRunner(prof, sent.append, 0.5, 2)
    io.values.update({"SENS_BOARD_ROT": 0.0})
    assert io.read_extra(0.0) and sent[-1].name == "CAL_GYRO0_ROT"
    for t in (0.6, 1.2):
        io.tick(t)
    assert io.done and io.error is None and prof.absent == {"CAL_GYRO0_ROT"}
    assert not io.read_extra(2.0)  # not asked again
