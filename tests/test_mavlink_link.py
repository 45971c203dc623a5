"""MavlinkLink against the virtual autopilot (``gyrocal sim --link mavlink``), over a pty and UDP."""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from gyrocal.daemon.ring import RingBuffer  # noqa: E402
from gyrocal.mavlink.link import MavlinkLink  # noqa: E402
from gyrocal.mavlink.poly import evaluate  # noqa: E402
from gyrocal.protocol.messages import (  # noqa: E402
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffWrite,
    Hello,
    NakReason,
    coeff_set_crc,
)
from gyrocal.protocol.termsets import TEMP_POLY2_ID, TEMP_POLY3_ID  # noqa: E402
from gyrocal.sim.autopilot import VirtualAutopilot  # noqa: E402
from tests.sim_helpers import SimProcess, free_udp_port, read_status, wait_for  # noqa: E402

pytestmark = pytest.mark.slow

Q = np.array([[0.05, 1e-3, -2e-5, 3e-7], [-0.02, -5e-4, 1e-5, 0.0], [0.01, 2e-4, 0.0, -1e-7]])


class Collector:
    def __init__(self) -> None:
        self.msgs: list[Any] = []
        self.events: list[tuple[str, str]] = []
        self.lock = threading.Lock()

    def control(self, m: Any) -> None:
        with self.lock:
            self.msgs.append(m)

    def event(self, name: str, detail: str) -> None:
        self.events.append((name, detail))

    def of(self, cls: type) -> list[Any]:
        with self.lock:
            return [m for m in self.msgs if isinstance(m, cls)]


def open_link(url: str, tmp_path: Path, **kw: Any) -> tuple[MavlinkLink, Collector, RingBuffer]:
    col = Collector()
    ring = RingBuffer(1 << 16)
    link = MavlinkLink(
        url, ring, col.control, col.event, state_file=str(tmp_path / "mav.json"),
        **{"param_timeout_s": 0.3, **kw},
    )
    link.start()
    return link, col, ring


def sim(kind: str, tmp_path: Path, *extra: str) -> SimProcess:
    return SimProcess(
        "--link",
        "mavlink",
        "--autopilot",
        kind,
        "--rate",
        "250",
        "--warmup-tau",
        "30",
        "--status-json",
        str(tmp_path / "ap.json"),
        "--flash",
        str(tmp_path / "ap-flash.json"),
        *extra,
        tmp_path=tmp_path,
    )


def param_becomes(tmp_path: Path, name: str, value: float) -> bool:
    """The sim writes its status every 0.5 s: wait until it shows the parameter at value."""
    return wait_for(lambda: read_status(tmp_path / "ap.json").get("params", {}).get(name) == value, 5)


def reconstruction_error_dps(ring: RingBuffer, report: CoeffReport, kind: str, boot: int) -> np.ndarray:
    """Mean over the samples in the ring of (out + Q_reported(T)) - true raw rate(T) [deg/s], per axis."""
    s = ring.pop()
    ap = VirtualAutopilot(kind, 250, 0)
    ap.boot_count = boot - 1
    ap.power_on()
    raw_true = ap.raw_offset_dps(s["temp"])
    out = np.column_stack([s["wx"], s["wy"], s["wz"]])
    rebuilt = out + evaluate(np.asarray(report.coeffs_dps), s["temp"])  # any prefix of the cubic
    return np.mean(rebuilt - raw_true, axis=0)


def test_px4_over_a_pty_hello_samples_push_and_reboot(tmp_path: Path) -> None:
    with sim("px4", tmp_path) as ap:
        link, col, ring = open_link(ap.address, tmp_path, autopilot="px4")
        try:
            assert wait_for(lambda: col.of(Hello), 15)
            hello = col.of(Hello)[0]
            assert hello.fw_version == "1.14.0" and hello.boot_count == 1 and hello.rate_hz == 250
            assert link.reboot_required is True  # TC_G_ENABLE was 0 at this boot
            assert (
                link.term_sets[TEMP_POLY3_ID] == ("1", "temp", "temp^2", "temp^3")
                and len(link.term_sets) == 3
            )
            assert wait_for(lambda: ring.pushed > 500, 15)
            link.send(CoeffRead())
            assert wait_for(lambda: col.of(CoeffReport), 10)
            first = col.of(CoeffReport)[0]
            assert first.version == 0 and np.all(np.asarray(first.coeffs_dps)[:, 1:] == 0)  # CAL offsets only
            link.send(CoeffWrite(7, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: col.of(CoeffAck) or col.of(CoeffNak), 15)
            assert col.of(CoeffAck) == [CoeffAck(7, coeff_set_crc(7, TEMP_POLY3_ID, Q))]
            link.send(CoeffRead())
            assert wait_for(lambda: len(col.of(CoeffReport)) == 2, 10)
            rep = col.of(CoeffReport)[1]
            assert rep.version == 7 and np.array_equal(np.asarray(rep.coeffs_dps), Q)
            assert param_becomes(tmp_path, "TC_G_ENABLE", 1.0)
            params = read_status(tmp_path / "ap.json")["params"]
            assert params["TC_G0_ID"] == params["CAL_GYRO0_ID"]
            # the set waits for a reboot: samples are made consistent with the reported set meanwhile
            ring.pop()
            assert wait_for(lambda: ring.pushed > ring.popped + 750, 15)
            err = reconstruction_error_dps(ring, rep, "px4", 1)
            assert np.all(np.abs(err) < 0.02), err
            link.reboot()
            assert wait_for(lambda: len(col.of(Hello)) == 2, 20)
            assert col.of(Hello)[1].boot_count == 2 and link.reboot_required is False
            link.send(CoeffRead())
            assert wait_for(lambda: len(col.of(CoeffReport)) == 3, 10)
            assert col.of(CoeffReport)[2].version == 7
        finally:
            link.stop()


def test_ardupilot_over_udp_push_survives_lost_echoes(tmp_path: Path) -> None:
    port = free_udp_port()
    with sim("ardupilot", tmp_path, "--mavlink-udp", f"127.0.0.1:{port}", "--drop-param-values", "2") as ap:
        assert ap.address == f"udpin:127.0.0.1:{port}"
        link, col, ring = open_link(ap.address, tmp_path)
        try:
            assert wait_for(lambda: col.of(Hello), 15)
            assert link.stats()["imu_source"] == "RAW_IMU" and link.reboot_required is False
            assert wait_for(lambda: ring.pushed > 500, 15)
            q2 = Q[:, :3]  # the quadratic prefix, as the daemon learns it: the link pads the cubic with 0
            link.send(CoeffWrite(3, TEMP_POLY2_ID, q2))
            assert wait_for(lambda: col.of(CoeffAck) or col.of(CoeffNak), 20)
            assert col.of(CoeffAck) == [CoeffAck(3, coeff_set_crc(3, TEMP_POLY2_ID, q2))]
            assert param_becomes(tmp_path, "INS_TCAL1_ENABLE", 1.0)
            link.send(CoeffRead())
            assert wait_for(lambda: col.of(CoeffReport), 10)
            rep = col.of(CoeffReport)[-1]
            assert rep.terms_id == TEMP_POLY2_ID and np.array_equal(np.asarray(rep.coeffs_dps), q2)
            ring.pop()
            assert wait_for(lambda: ring.pushed > ring.popped + 1000, 15)
            err = reconstruction_error_dps(ring, rep, "ardupilot", 1)
            # RAW_IMU is int16 mrad/s truncated toward zero: a mean is exact only to ~1 LSB (0.057 deg/s)
            assert np.all(np.abs(err) < 0.06), err
        finally:
            link.stop()


def test_a_rejected_value_naks_and_the_old_set_stays(tmp_path: Path) -> None:
    with sim("px4", tmp_path, "--reject-param", "TC_G0_X2_1") as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="px4")
        try:
            streaming(link, col)
            link.send(CoeffWrite(4, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: col.of(CoeffAck) or col.of(CoeffNak), 15)
            nak = col.of(CoeffNak)
            assert nak and nak[0].version == 4 and nak[0].reason == NakReason.OUT_OF_RANGE
            assert param_becomes(tmp_path, "TC_G0_X1_0", 0.0)  # restored: the old (empty) set, still off
            assert read_status(tmp_path / "ap.json")["params"]["TC_G_ENABLE"] == 0
            link.send(CoeffRead())
            assert wait_for(lambda: col.of(CoeffReport), 10)
            assert col.of(CoeffReport)[0].version == 0
        finally:
            link.stop()


def streaming(link: MavlinkLink, col: Collector) -> None:
    """The autopilot said who it is (HELLO) and has streamed more than 300 samples."""
    assert wait_for(lambda: col.of(Hello), 15)
    assert wait_for(lambda: link.stats()["samples"] > 300, 15)


def push_into_a_reboot(link: MavlinkLink, col: Collector) -> None:
    """Push v5 into an autopilot that reboots during it: NAKed BUSY, then the new boot's HELLO."""
    streaming(link, col)
    link.send(CoeffWrite(5, TEMP_POLY3_ID, Q))
    assert wait_for(lambda: col.of(CoeffAck) or col.of(CoeffNak), 20)
    assert not col.of(CoeffAck) and col.of(CoeffNak)[0].reason == NakReason.BUSY
    assert wait_for(lambda: len(col.of(Hello)) == 2, 20)
    assert col.of(Hello)[1].boot_count == 2


def push_v5_over_a_held_v4(link: MavlinkLink, col: Collector) -> None:
    """v4 pushed and acked, then v5 pushed into a fault that cuts it: NAKed."""
    streaming(link, col)
    link.send(CoeffWrite(4, TEMP_POLY3_ID, Q))
    assert wait_for(lambda: col.of(CoeffAck), 15)
    link.send(CoeffWrite(5, TEMP_POLY3_ID, Q * 1.5))
    assert wait_for(lambda: col.of(CoeffNak), 20)


def test_a_reboot_mid_push_naks_and_leaves_no_partial_set(tmp_path: Path) -> None:
    with sim("ardupilot", tmp_path, "--reboot-after-sets", "6") as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="ardupilot")
        try:
            push_into_a_reboot(link, col)
            # ENABLE=0 was written first: the partial coefficients are not applied after the reboot
            assert param_becomes(tmp_path, "INS_TCAL1_ENABLE", 0.0)
        finally:
            link.stop()


@pytest.mark.parametrize("reboot_at", [5, 18], ids=["at_a_coefficient", "at_enable"])
def test_a_px4_reboot_mid_push_is_never_acked_as_applied(tmp_path: Path, reboot_at: int) -> None:
    """The PX4 reboots at the 5th PARAM_SET (a coefficient): silent 1.5 s, then it forgets its
    streams. The resent request used to land in the new boot with the rest of the set, the read-back
    matched, and v5 was acked as stored, while that boot had begun with TC_G_ENABLE = 0 (written
    first) and applied none of it (an integrator's audit). Now the push waits for the autopilot's
    clock between requests, sees it went back, and NAKs; the new boot says a push needs a reboot and
    reports no set; the same version pushed again is acked, waiting for the reboot.

    At the 18th write (ENABLE = 1, after DISABLE and the 16 set parameters) the write lands and its
    echo is lost to the reboot: the new boot holds the whole set, enabled, so it is reported as v5
    (the daemon records it applied, ack lost), not as a set gyrocal did not write."""
    whole = reboot_at == 18
    with sim("px4", tmp_path, "--reboot-after-sets", str(reboot_at)) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="px4", param_timeout_s=0.5)
        try:
            push_into_a_reboot(link, col)
            assert link.reboot_required is (not whole)
            assert param_becomes(tmp_path, "TC_G_ENABLE", 1.0 if whole else 0.0)
            link.send(CoeffRead())
            assert wait_for(lambda: col.of(CoeffReport), 10)
            assert col.of(CoeffReport)[0].version == (5 if whole else 0)
            link.send(CoeffWrite(5, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: col.of(CoeffAck), 20)
            assert col.of(CoeffAck) == [CoeffAck(5, coeff_set_crc(5, TEMP_POLY3_ID, Q))]
            assert link.reboot_required is (not whole)
        finally:
            link.stop()


def test_a_write_resent_while_its_push_runs_gets_that_push_s_answer_not_busy(tmp_path: Path) -> None:
    """Lost echoes stretch a push past the host's ack timeout; the host resends the same write. Each
    write gets one answer (protocol.md), the running push's own: two ACKs, no BUSY."""
    with sim("px4", tmp_path, "--drop-param-values", "3") as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="px4", param_timeout_s=0.5)
        try:
            streaming(link, col)
            assert link.capabilities.ack_within_s == 4 * 0.5 * 4
            link.send(CoeffWrite(5, TEMP_POLY3_ID, Q))
            assert not wait_for(lambda: col.of(CoeffAck) or col.of(CoeffNak), 1.0)  # still running
            link.send(CoeffWrite(5, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: len(col.of(CoeffAck)) == 2, 20)
            assert not col.of(CoeffNak)
        finally:
            link.stop()


def test_a_link_stopped_mid_push_lets_the_push_end_first(tmp_path: Path) -> None:
    """ENABLE = 0 is written first: a daemon stopped during the coefficient writes left an ArduPilot
    with its compensation off until the next push. The link's stop now lets the push end."""
    with sim("ardupilot", tmp_path) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="ardupilot")
        stopped = False
        try:
            streaming(link, col)
            link.send(CoeffWrite(5, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: link._push is not None and link._push.phase.value == "write", 10, 0.001)
            link.stop()
            stopped = True
            assert col.of(CoeffAck) == [CoeffAck(5, coeff_set_crc(5, TEMP_POLY3_ID, Q))]
            assert param_becomes(tmp_path, "INS_TCAL1_ENABLE", 1.0)
        finally:
            if not stopped:
                link.stop()


def test_a_board_rotation_changed_while_idle_starts_a_new_session(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A ground station writes AHRS_ORIENTATION between pushes: the samples are then in a new body
    frame, and nothing was said (the next set was pushed 14 s later: an integrator's audit). The idle
    check reads it; the link declares a new boot, so the daemon starts a new session, cold
    (capabilities.frame_changed), and a write of the old session's set meanwhile is refused."""
    from gyrocal.mavlink import link as link_mod
    from gyrocal.mavlink.paramtx import ParamSet
    from gyrocal.mavlink.profiles import INT8, encode_param

    monkeypatch.setattr(link_mod, "CHECK_EVERY_S", 1.0)
    with sim("ardupilot", tmp_path) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="ardupilot")
        try:
            assert wait_for(lambda: col.of(Hello), 15)
            first = col.of(Hello)[0]
            assert link.capabilities.board_rotation == {"AHRS_ORIENTATION": 0.0}
            with link._write_lock:
                link._send_param(ParamSet("AHRS_ORIENTATION", encode_param(8.0, INT8, False), INT8))
            assert wait_for(lambda: len(col.of(Hello)) == 2, 15)
            again = col.of(Hello)[1]
            assert again.serial == first.serial and again.boot_count == first.boot_count + 1
            assert link.capabilities.board_rotation == {"AHRS_ORIENTATION": 8.0}
            assert read_status(tmp_path / "ap.json")["boot"] == 1  # the autopilot did not reboot
        finally:
            link.stop()


def test_a_rollback_goes_back_with_the_range_its_version_was_written_with(tmp_path: Path) -> None:
    """The range seen widens as the board warms; v5 written over the first range, pushed again later
    (a rollback), went back with the wider TMIN/TMAX: extrapolated, where the autopilot clamps
    (an integrator's audit). A version the autopilot held keeps its own range."""
    with sim("ardupilot", tmp_path) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="ardupilot")
        try:
            streaming(link, col)
            link.send(CoeffWrite(5, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: col.of(CoeffAck), 15)
            assert wait_for(lambda: read_status(tmp_path / "ap.json")["params"]["INS_TCAL1_ENABLE"] == 1, 5)
            first = {k: read_status(tmp_path / "ap.json")["params"][k] for k in ("INS_TCAL1_TMIN",
                                                                                 "INS_TCAL1_TMAX")}
            link.state.widen(link.serial, first["INS_TCAL1_TMIN"] - 5.0, first["INS_TCAL1_TMAX"] + 5.0)
            link.send(CoeffWrite(6, TEMP_POLY3_ID, Q * 1.01))
            assert wait_for(lambda: len(col.of(CoeffAck)) == 2, 15)
            def tmax_near(v: float, tol: float = 0.01) -> bool:
                return wait_for(lambda: abs(read_status(tmp_path / "ap.json")["params"]["INS_TCAL1_TMAX"] - v)
                                < tol, 5)

            assert tmax_near(first["INS_TCAL1_TMAX"] + 5.0, tol=0.15)  # v6: the widened range
            link.send(CoeffWrite(5, TEMP_POLY3_ID, Q))  # the rollback
            assert wait_for(lambda: len(col.of(CoeffAck)) == 3, 15)
            assert tmax_near(first["INS_TCAL1_TMAX"])
            assert read_status(tmp_path / "ap.json")["params"]["INS_TCAL1_TMIN"] == first["INS_TCAL1_TMIN"]
        finally:
            link.stop()


def test_a_vehicle_armed_mid_push_gets_no_further_write(tmp_path: Path) -> None:
    """The push wrote the set to the end and acked it while the vehicle was armed (an integrator's
    audit). Armed mid-push, the link writes nothing more and NAKs BUSY (a resend is refused while
    armed, as at any push start)."""
    from gyrocal.mavlink.paramtx import ParamPush, ParamSet
    from gyrocal.mavlink.profiles import ArduPilot

    class Heartbeat:
        autopilot, base_mode = 3, 128  # ArduPilot, MAV_MODE_FLAG_SAFETY_ARMED

        def get_srcComponent(self) -> int:
            return 1

        def get_srcSystem(self) -> int:
            return 1

    sent: list[object] = []
    link = MavlinkLink("udpin:127.0.0.1:0", RingBuffer(1 << 10), lambda m: None, state_file=None,
                       autopilot="ardupilot")
    link.target_system, link.serial = 1, 42
    link._boot.last_hb, link._stream_asked_at = 0.0, 0.0
    link._push = ParamPush(ArduPilot(0), Q, 20.0, 50.0, sent.append, 0.0)
    link._push_write, link._push_range = CoeffWrite(5, TEMP_POLY3_ID, Q), (20.0, 50.0)
    out: list[object] = []
    link._on_heartbeat(Heartbeat(), 0.5, out)
    assert link._push is None and [type(m) for m in out] == [CoeffNak] and out[0].reason == NakReason.BUSY
    assert not [m for m in sent if isinstance(m, ParamSet)]  # nothing written
    assert link.armed


def test_a_push_cut_by_a_reboot_puts_back_the_set_held_before(tmp_path: Path) -> None:
    """v4 is held and enabled; the push of v5 writes ENABLE = 0, then the PX4 reboots at its 23rd
    PARAM_SET (v4 took 18: DISABLE, 16 parameters, ENABLE). It booted with its compensation off and
    part of v5, worse than before the push (a re-audit). The link writes v4 back before the new
    boot's HELLO: the new session reads v4, waiting for the next reboot."""
    with sim("px4", tmp_path, "--reboot-after-sets", "23") as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="px4", param_timeout_s=0.5)
        try:
            push_v5_over_a_held_v4(link, col)
            assert wait_for(lambda: len(col.of(Hello)) == 2, 20)
            assert param_becomes(tmp_path, "TC_G_ENABLE", 1.0)
            link.send(CoeffRead())
            assert wait_for(lambda: col.of(CoeffReport), 10)
            rep = col.of(CoeffReport)[0]
            assert rep.version == 4 and np.allclose(rep.coeffs_dps, Q) and link.reboot_required is True
        finally:
            link.stop()


def test_a_lost_autopilot_version_is_asked_for_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without AUTOPILOT_VERSION no HELLO is said; its answer lost on a busy pty (a full pty drops
    bytes), the daemon waited for a HELLO forever (seen in CI under load). It is asked for again."""
    from gyrocal.mavlink import link as link_mod

    link = MavlinkLink("udpin:127.0.0.1:0", RingBuffer(1 << 10), lambda m: None, state_file=None,
                       autopilot="ardupilot")
    asked: list[tuple] = []
    monkeypatch.setattr(link, "_command", lambda *a: asked.append(a))
    link._stream_asked_at = link._version_asked_at = 0.0
    link._reader = None
    def version_asks() -> list[tuple]:
        return [a for a in asked if a[0] == link_mod.CMD_REQUEST_MESSAGE]

    link._tick(link_mod.VERSION_ASK_S / 2, [])
    assert not version_asks()
    link._tick(link_mod.VERSION_ASK_S + 0.1, [])
    assert version_asks() == [(link_mod.CMD_REQUEST_MESSAGE, link_mod.MSG_ID["AUTOPILOT_VERSION"])]


def test_a_wrong_autopilot_type_is_one_clear_fault(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with sim("ardupilot", tmp_path) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="px4")
        try:
            assert wait_for(lambda: link.fault is not None, 15)
            assert "ardupilot" in link.fault and "px4" in link.fault
            assert [e for e in col.events if e[0] == "unit_error"][:1] and not col.of(Hello)
            link.send(CoeffWrite(1, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: col.of(CoeffNak), 5)
            assert col.of(CoeffNak)[0].reason == NakReason.UNKNOWN_TERMS
        finally:
            link.stop()
        errors = [r for r in caplog.records if r.levelname == "ERROR" and "MAV_AUTOPILOT" in r.getMessage()]
        assert len(errors) == 1


def test_each_boot_of_a_run_starts_at_its_own_ambient() -> None:
    """``--ambient 20,30``: the second warm-up is on a hotter day (issue 10: merge across switch-ons),
    and the boot gyro calibration of an ArduPilot is taken at that boot's own temperature."""
    ap = VirtualAutopilot("ardupilot", 250, 0, ambients_c=(20.0, 30.0))
    temps, caltemps = [], []
    for _ in range(3):
        ap.power_on()
        temps.append(ap.temp_c(0.0))
        caltemps.append(ap.params["INS_GYR1_CALTEMP"])
    assert temps == [20.0, 30.0, 30.0] and caltemps == pytest.approx([20.0, 30.0, 30.0])
    assert ap.temp_c(1e4) == pytest.approx(60.0)  # each rises 30 degC



def test_the_boot_detector_after_a_heartbeat_silence() -> None:
    """A reboot after a running stream is a new boot (its clock goes back); stamps that continue the
    old clock are the same boot, as after a host that stalled for 4 s and then reads what the OS kept
    for it (a rule that asked the clock to have run on by the silence took those for a reboot); with
    no stamp at all after the silence, the suspicion counts as a boot after silence_s."""
    from gyrocal.mavlink.imu import BootDetector

    b = BootDetector(silence_s=3.0)
    b.on_heartbeat(0.0)
    assert not b.on_time(5.0)
    assert not b.on_heartbeat(4.1)  # 4.1 s of silence: suspicion
    assert b.on_time(0.05)  # the clock restarted: a new boot
    stall = BootDetector(silence_s=3.0)
    stall.on_heartbeat(0.0)
    assert not stall.on_time(5.0)
    assert not stall.on_heartbeat(4.1)
    assert not stall.on_time(5.01) and not stall.on_time(5.02)  # buffered stamps: the same boot
    assert not stall.on_heartbeat(5.1) and not stall.on_heartbeat(8.2)
    quiet = BootDetector(silence_s=3.0)
    quiet.on_heartbeat(0.0)
    assert not quiet.on_heartbeat(4.1)
    assert not quiet.on_heartbeat(5.1) and not quiet.on_heartbeat(6.1)
    assert quiet.on_heartbeat(7.2)


def test_a_daemon_restarted_before_the_px4_reboots_still_knows_the_set_waits_for_it(tmp_path: Path) -> None:
    """v7 is written to a PX4 whose TC_G_ENABLE was off at boot: it applies nothing until a reboot.
    A link opened again in the same boot (a daemon restart) read the parameters after those writes,
    took v7 for applied and stopped correcting the samples; the next set was learnt on that (an
    autopilot integrator's audit). The parameters at the boot's start are kept per boot."""
    with sim("px4", tmp_path) as ap:
        link, col, ring = open_link(ap.address, tmp_path, autopilot="px4")
        try:
            assert wait_for(lambda: col.of(Hello), 15) and link.reboot_required is True
            assert wait_for(lambda: ring.pushed > 500, 15)
            link.send(CoeffRead())
            assert wait_for(lambda: col.of(CoeffReport), 10)
            link.send(CoeffWrite(7, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: col.of(CoeffAck) or col.of(CoeffNak), 15) and col.of(CoeffAck)
            assert param_becomes(tmp_path, "TC_G_ENABLE", 1.0)
        finally:
            link.stop()
        link, col, ring = open_link(ap.address, tmp_path, autopilot="px4")  # the daemon restarted
        try:
            assert wait_for(lambda: col.of(Hello), 15)
            assert col.of(Hello)[0].boot_count == 1 and link.reboot_required is True
            link.send(CoeffRead())
            assert wait_for(lambda: col.of(CoeffReport), 10)
            rep = col.of(CoeffReport)[0]
            assert rep.version == 7
            ring.pop()
            assert wait_for(lambda: ring.pushed > ring.popped + 750, 15)
            err = reconstruction_error_dps(ring, rep, "px4", 1)  # samples as if v7 were applied
            assert np.all(np.abs(err) < 0.02), err
        finally:
            link.stop()


def test_a_fault_of_the_last_boot_is_judged_again_at_a_new_boot(tmp_path: Path) -> None:
    """The autopilot vanished mid-push: the restore's read failed ('no PARAM_VALUE'), and that fault
    outlived the autopilot's return, so the link never said HELLO again and the daemon sat in
    UNIT_SILENT until restarted (an integrator's audit). A new boot clears it; this boot's reads and
    heartbeats set again whatever still holds."""
    col = Collector()
    link = MavlinkLink("udpin:127.0.0.1:1", RingBuffer(1 << 10), col.control, col.event,
                       state_file=str(tmp_path / "mav.json"), autopilot="px4")
    link._set_fault("cannot read px4 compensation parameters: no PARAM_VALUE after 4 read request(s)")
    assert link.fault is not None and not link._ready()
    link._new_boot([], "heartbeat returned after silence")
    assert link.fault is None and link._known_new


def test_a_constant_alone_is_written_about_a_steady_temperature_and_a_curve_is_not(tmp_path: Path) -> None:
    """A board held at 50 degC from switch-on (an IMU heater): a set with temperature terms over a
    range narrower than 1 degC is refused (never extrapolated); a constant alone, the same at any
    temperature, is written with TMIN..TMAX widened to 1 degC about the temperature seen; a set whose
    own range the operator gave is written with that."""
    with SimProcess("--link", "mavlink", "--autopilot", "px4", "--rate", "250", "--ambient", "50",
                    "--rise", "0", "--status-json", str(tmp_path / "ap.json"), tmp_path=tmp_path) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="px4")
        try:
            streaming(link, col)
            link.send(CoeffWrite(4, TEMP_POLY2_ID, Q[:, :3]))
            assert wait_for(lambda: col.of(CoeffNak), 15)
            assert col.of(CoeffNak)[0].reason == NakReason.OUT_OF_RANGE
            const = np.zeros((3, 3))
            const[:, 0] = [0.2, -0.05, 0.08]
            link.send(CoeffWrite(5, TEMP_POLY2_ID, const))
            assert wait_for(lambda: col.of(CoeffAck), 15), col.msgs
            assert col.of(CoeffAck)[0].version == 5
            assert param_becomes(tmp_path, "TC_G_ENABLE", 1.0)
            p = read_status(tmp_path / "ap.json")["params"]
            lo, hi = p["TC_G0_TMIN"], p["TC_G0_TMAX"]
            assert hi - lo >= 1.0 - 1e-4 and lo < 50.0 < hi
            assert p["TC_G0_X1_0"] == p["TC_G0_X2_0"] == 0.0
            # an operator's file that says its set was learnt over 22..30 degC (push --file of a fit or
            # a store record) is written with that range, not the one seen now
            link.hold_range(6, 22.0, 30.0)
            link.send(CoeffWrite(6, TEMP_POLY2_ID, Q[:, :3]))
            assert wait_for(lambda: len(col.of(CoeffAck)) == 2, 15), col.msgs
            assert param_becomes(tmp_path, "TC_G0_TMAX", 30.0)
            assert read_status(tmp_path / "ap.json")["params"]["TC_G0_TMIN"] == 22.0
        finally:
            link.stop()


def test_a_push_cut_by_a_hang_puts_back_the_set_held_before_when_the_autopilot_answers(
        tmp_path: Path) -> None:
    """v4 is held and enabled; the push of v5 writes ENABLE = 0, then the ArduPilot hangs at its 23rd
    PARAM_SET for 5 s (no reboot: the same boot goes on). The push is NAKed BUSY on the lost
    heartbeat, and the daemon asks at once what the unit holds, as its session does. That read, cut
    by the hang, used to become a link fault: every later write was NAKed UNKNOWN_TERMS (final), and
    the autopilot flew on with its compensation off until the next switch-on. Now the read waits
    for the autopilot to answer; the link writes v4 back, reports v4, enabled, and the same v5
    pushed again is acked."""
    with sim("ardupilot", tmp_path, "--silence-after-sets", "23", "--silence-for", "5") as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="ardupilot", param_timeout_s=0.5)
        try:
            push_v5_over_a_held_v4(link, col)
            assert col.of(CoeffNak)[0].reason == NakReason.BUSY
            link.send(CoeffRead())
            assert wait_for(lambda: col.of(CoeffReport), 20)
            rep = col.of(CoeffReport)[-1]  # its constant holds the ArduPilot's own gyro offsets
            assert rep.version == 4 and np.allclose(np.asarray(rep.coeffs_dps)[:, 1:], Q[:, 1:], atol=1e-6)
            assert param_becomes(tmp_path, "INS_TCAL1_ENABLE", 1.0)
            assert link.fault is None and len(col.of(Hello)) == 1  # the same boot, no fault
            link.send(CoeffWrite(5, TEMP_POLY3_ID, Q * 1.5))
            assert wait_for(lambda: len(col.of(CoeffAck)) == 2, 20)
            assert col.of(CoeffAck)[1].version == 5 and len(col.of(CoeffNak)) == 1
        finally:
            link.stop()


def test_a_ground_station_s_write_of_the_compensation_is_reported_unasked(tmp_path: Path) -> None:
    """After v4 was acked, a ground station wrote INS_TCAL1_ENABLE = 0. The link went on reporting v4,
    the daemon rebuilt the raw rate with it, learnt a curve doubled by it and pushed a set worse than
    none (an integrator's audit). The autopilot's broadcast PARAM_VALUE makes the link read at once,
    and report the set it holds (v0) unasked."""
    from gyrocal.mavlink.paramtx import ParamSet, encode_param

    with sim("ardupilot", tmp_path) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="ardupilot")
        try:
            streaming(link, col)
            link.send(CoeffWrite(4, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: col.of(CoeffAck), 15)
            enable = link.profile.enable
            link._send_param(ParamSet(enable.name, encode_param(0.0, enable.ptype, link.profile.bytewise),
                                      enable.ptype))  # written behind the link's back, as another GCS does
            assert param_becomes(tmp_path, "INS_TCAL1_ENABLE", 0.0)
            assert wait_for(lambda: col.of(CoeffReport), 5)  # well before the 10 s idle check
            assert col.of(CoeffReport)[0].version == 0
        finally:
            link.stop()


def test_an_ardupilot_learning_its_own_temperature_calibration_is_left_alone(tmp_path: Path, caplog) -> None:
    """INS_TCAL1_ENABLE = 2: ArduPilot's own learning run, which its user started from a cold board.
    The first push wrote ENABLE = 0 and ended it unseen (an integrator's audit). Writes are NAKed BUSY
    with the reason until the run ends; the same version refused for the same reason again is INFO."""
    import json as _json

    flash = {"params": {"INS_TCAL1_ENABLE": 2.0}, "boot_count": 0}
    (tmp_path / "ap-flash.json").write_text(_json.dumps(flash))
    with sim("ardupilot", tmp_path) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="ardupilot")
        try:
            streaming(link, col)
            link.send(CoeffWrite(4, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: col.of(CoeffNak), 10)
            assert col.of(CoeffNak)[0].reason == NakReason.BUSY and not col.of(CoeffAck)
            assert param_becomes(tmp_path, "INS_TCAL1_ENABLE", 2.0)
            assert "learning its own temperature calibration" in link.stats()["hold"]  # status's reason
            # the run ends (ArduPilot sets 1): its set stands for the boot. Replaced within the second,
            # an ArduPilot's 8/6/3 deg/h became gyrocal's 22/15/17 (an integrator's re-check)
            from gyrocal.mavlink.paramtx import ParamSet, encode_param

            enable = link.profile.enable
            link._send_param(ParamSet(enable.name, encode_param(1.0, enable.ptype, link.profile.bytewise),
                                      enable.ptype))
            assert wait_for(lambda: "ended its own" in (link.stats()["hold"] or ""), 10)
            link.send(CoeffWrite(5, TEMP_POLY3_ID, Q))
            assert wait_for(lambda: len(col.of(CoeffNak)) == 2, 10)
            assert col.of(CoeffNak)[1].reason == NakReason.BUSY and not col.of(CoeffAck)
            caplog.set_level(logging.INFO)
            caplog.clear()
            link.send(CoeffWrite(5, TEMP_POLY3_ID, Q))  # the daemon's retry round
            assert wait_for(lambda: len(col.of(CoeffNak)) == 3, 10)
            said = [r for r in caplog.records if "push of v5 refused" in r.getMessage()]
            assert len(said) == 1 and said[0].levelno == logging.INFO
            assert "refused again" in said[0].getMessage()
        finally:
            link.stop()


def test_an_imu_the_autopilot_does_not_have_is_a_fault_that_names_the_instance(tmp_path: Path) -> None:
    """instance: 1 on a one-IMU autopilot. Status said WAIT_HELLO "0 samples received" for good, which
    sends an operator to the cable (an integrator's audit). Without its parameters (the virtual
    autopilots have one IMU), the read fault names the instance; with them but no message of that IMU
    for 10 s of heartbeats, so does the link's fault."""
    from gyrocal.mavlink import link as link_mod

    with sim("px4", tmp_path) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="px4", instance=1)
        try:
            assert wait_for(lambda: link.fault is not None, 20)
            assert "TC_G1_" in link.fault and "link.mavlink.instance" in link.fault and not col.of(Hello)
        finally:
            link.stop()
    lk = MavlinkLink("udpin:127.0.0.1:0", RingBuffer(1 << 10), lambda m: None, state_file=None,
                     autopilot="ardupilot", instance=1)
    lk._stream_asked_at, lk._boot.last_hb, lk._version_asked_at = 0.0, link_mod.NO_IMU_S, link_mod.NO_IMU_S
    lk._reader, lk._source = None, "SCALED_IMU2"
    lk._command = lambda *a: None  # type: ignore[method-assign]  # no connection here
    lk._tick(link_mod.NO_IMU_S + 0.5, [])
    assert lk.fault is not None and "IMU 1" in lk.fault and "SCALED_IMU2" in lk.fault


def test_a_px4_external_gyro_with_its_own_rotation_is_refused(tmp_path: Path) -> None:
    """CAL_GYRO0_ROT = 4: an external gyro follows its own rotation, not SENS_BOARD_ROT. The set,
    learnt and written in the board frame, was applied with x and y of the wrong sign (1957/1379
    deg/h left against 1136/821 uncompensated) while status said "agree" (an integrator's audit).
    It is a fault naming the parameter; an internal gyro (-1) is served as before."""
    import json as _json

    (tmp_path / "ap-flash.json").write_text(_json.dumps({"params": {"CAL_GYRO0_ROT": 4.0}, "boot_count": 0}))
    with sim("px4", tmp_path) as ap:
        link, col, _ = open_link(ap.address, tmp_path, autopilot="px4")
        try:
            assert wait_for(lambda: link.fault is not None, 20)
            assert "CAL_GYRO0_ROT = 4" in link.fault and not col.of(Hello)
        finally:
            link.stop()


def test_a_retry_of_a_version_is_written_with_the_range_of_its_first_push() -> None:
    """v2, learnt over 20-43.5 degC, was cut short; its retry, after the temperature had reached 47.1,
    went out with TMAX 47.1 while its record said 43.5, and no refinement followed: 300-400 deg/h left
    at 50 degC (an integrator's re-check). A version keeps the range of its first push."""
    link = MavlinkLink("udpin:127.0.0.1:0", RingBuffer(1 << 10), lambda m: None, state_file=None,
                       autopilot="ardupilot")
    link.serial, link.target_system = 42, 1
    link._hello = Hello(42, "4.5.7", 1, 250)
    link._send_param = lambda req: None  # type: ignore[method-assign]  # no connection here
    link._range = [20.0, 43.5]
    link._start_push(CoeffWrite(2, TEMP_POLY3_ID, Q), 0.0, [])
    first = link._push_range
    link._push = link._push_write = None  # cut short
    link._range = [20.0, 47.1]
    link._start_push(CoeffWrite(2, TEMP_POLY3_ID, Q), 10.0, [])
    assert link._push_range == first == (20.0, 43.5)
    link._push = link._push_write = None
    link._start_push(CoeffWrite(3, TEMP_POLY3_ID, Q * 1.1), 20.0, [])  # a new version: the range seen
    assert link._push_range == (20.0, 47.1)
