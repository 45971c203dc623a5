"""Issue 8: the daemon never dies and never lies. Faults in the session (simulated time, the real
estimator, store and unit logic), in the sequence tracker, and a few fast scenarios of the fault
campaign (benchmarks/faults.py) against real processes."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gyrocal.daemon.reconcile import close_abandoned
from gyrocal.daemon.restart import SeqTracker
from gyrocal.daemon.ring import SAMPLE_DTYPE
from gyrocal.daemon.session import State
from gyrocal.daemon.store import CalibrationRecord, CalibrationStore
from gyrocal.errors import LinkError
from gyrocal.protocol.messages import CoeffReport
from gyrocal.protocol.serial_framing import FrameDecoder
from gyrocal.protocol.termsets import SEED000_ID
from gyrocal.sim.transports import nan_report_frame
from gyrocal.sim.unit import Faults, NanReport
from tests.daemon_harness import Harness


def _pushed(h: Harness) -> bool:
    return h.session is not None and bool(h.session.last_push)


def _acked(h: Harness) -> bool:
    return h.session is not None and h.session.last_push.get("status") == "acked"


def _unplugged(msg: Any) -> None:
    """A link's send with the cable out: it raises, as the serial and CAN links do."""
    raise LinkError("serial link to /dev/ttyUSB0 is down; the message was not sent")


# ---- containment ------------------------------------------------------------------------------
def test_the_link_failing_mid_push_becomes_a_record_not_an_exception(tmp_path: Path) -> None:
    h = Harness.make(tmp_path, faults=Faults(drop_acks=100))
    h.switch_on()
    h.run(90, until=lambda h: h.session is not None and h.session.state is State.PUSHING)
    s = h.session
    assert s is not None and s.state is State.PUSHING

    s.send = _unplugged
    h.run(30, until=_pushed)  # must not raise
    assert s.last_push["status"] in ("link_down", "timeout")
    assert s.state is not State.PUSHING and s.send_failures > 0
    rec = h.store.get(4242, s.last_push["version"])
    assert rec is not None and rec.push["status"] == s.last_push["status"]


def test_a_push_into_a_link_that_takes_nothing_ends_link_down(tmp_path: Path) -> None:
    """protocol.md: a push ends 'link_down' when no write could be sent. The session's send reports a
    dead link by returning False (it logs the outage once), which the push took for a sent write: it
    waited out every ack and ended 'timeout' (an operator's audit, a rollback with the unit out)."""
    h = Harness.make(tmp_path)
    h.switch_on()
    h.run(90, until=_acked)
    s = h.session
    rec = h.store.get(4242, s.last_push["version"])

    s.send = _unplugged
    assert s.start_push(rec.version, list(rec.terms), np.asarray(rec.coefficients_dps), h.now) is None
    h.run(30, until=lambda hh: hh.session.push is None)
    assert s.last_push["status"] == "link_down" and s.push is None
    assert h.store.get(4242, rec.version).push["status"] == "acked"  # it was held before: it stays


def test_a_nan_read_back_is_refused_counted_and_asked_again_and_learning_goes_on(tmp_path: Path) -> None:
    h = Harness.make(tmp_path)
    h.switch_on()
    s = h.session
    assert s is not None
    nan = ((float("nan"),) * 10,) * 3
    s.on_message(CoeffReport(0, SEED000_ID, nan), h.now)  # a decoder that let it through
    assert s.refused_reports == 1 and s.applied is None and "NaN" in s.reason
    h.run(20)
    assert s.applied is not None and s.learner.samples > 0


def test_the_serial_decoder_drops_and_counts_a_nan_report() -> None:
    dec = FrameDecoder()
    assert dec.feed(nan_report_frame(NanReport(3, SEED000_ID, 10))) == []
    assert dec.stats.bad_values == 1 and dec.stats.crc_errors == 0


def test_an_unwritable_store_defers_the_push_and_it_goes_out_when_the_store_returns(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    h = Harness.make(tmp_path)
    real_add = h.store.add

    def disk_full(rec: CalibrationRecord) -> CalibrationRecord:
        raise OSError(28, "No space left on device")

    h.store.add = disk_full  # type: ignore[method-assign]
    h.switch_on()
    with caplog.at_level("INFO", logger="gyrocal.session"):
        h.run(60, until=lambda h: h.session is not None and h.session.store_error is not None)
        h.run(60)  # a minute of a full disk: one line for it, not one per retry (an operator's audit)
    s = h.session
    assert s is not None and s.store_error is not None
    assert "store unavailable" in s.status()["faults"]["store"]
    said = [r.getMessage() for r in caplog.records]
    assert sum("store unavailable" in m for m in said) == 1, said
    assert sum("estimator converged" in m for m in said) == 1, said
    assert h.unit.writes == {"acked": 0, "naked": 0, "dropped": 0, "acks_lost": 0}  # never an unknown set
    h.store.add = real_add  # type: ignore[method-assign]
    h.run(60, until=_acked)
    assert _acked(h) and h.store.latest(4242).push["status"] == "acked"


def test_a_refused_push_never_freezes_the_session(tmp_path: Path) -> None:
    h = Harness.make(tmp_path)
    h.switch_on()
    h.run(5)
    s = h.session
    assert s is not None
    before = s.state
    why = s.start_push(7, [f"t{k}" for k in range(22)], np.zeros((3, 22)), h.now)
    assert why is not None and "22 terms" in why
    assert s.state is before and s.push is None and s.last_push["status"] == "refused"
    h.run(90, until=_acked)  # and the session still calibrates
    assert _acked(h)


def test_a_busy_storm_retries_the_same_version_with_back_off(tmp_path: Path) -> None:
    h = Harness.make(tmp_path, faults=Faults(nak_next=6))
    h.switch_on()
    h.run(180, until=_acked)
    assert _acked(h)
    versions = [r.version for r in h.store.history(4242)]
    assert versions == [1], versions  # 6 NAKs, 2 failed rounds: still one version
    assert h.unit.writes["naked"] == 6


def test_a_push_acked_after_a_nak_records_no_nak_reason(tmp_path: Path) -> None:
    """One NAK BUSY, then the ack in the same push: the record said status acked, nak_reason 4 (found by
    a unit built from docs/protocol.md alone). The NAK stays in its reasons."""
    h = Harness.make(tmp_path, faults=Faults(nak_next=1))
    h.switch_on()
    h.run(120, until=_acked)
    push = h.store.get(4242, 1).push
    assert push["status"] == "acked" and push["attempts"] == 2 and push["nak_reason"] is None, push
    assert any("NAK" in r for r in push["reasons"])


# ---- reconciliation -----------------------------------------------------------------------------
def test_a_lost_ack_is_reconciled_from_the_read_back(tmp_path: Path) -> None:
    h = Harness.make(tmp_path, faults=Faults(lose_ack=3))
    h.switch_on()
    h.run(90, until=_pushed)
    s = h.session
    assert s is not None and s.last_push["status"] == "timeout"
    h.run(10, until=lambda h: h.store.get(4242, 1).push["status"] == "applied_ack_lost")
    rec = h.store.get(4242, 1)
    assert rec.push["status"] == "applied_ack_lost" and rec.push["history"][0]["status"] == "timeout"
    assert h.store.latest(4242, acked_only=True).version == 1  # warm start and rollback may use it
    assert s.status()["unit_set"]["agree"]
    # status's last_push follows the store's record: it kept saying 'timeout', readback_ok false, for a
    # set the unit holds (a serial integrator's unplug mid-push)
    lp = s.status()["last_push"]
    assert lp["status"] == "applied_ack_lost" and lp["readback_ok"] is True and lp["acked_crc"] is not None


def test_start_closes_abandoned_pushes_and_removes_leftover_temporaries(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    rec = store.add(CalibrationRecord(serial=9, version=0, terms=["1"], coefficients_dps=[[0.0]] * 3,
                                      uncertainty_dps=[[None]] * 3))
    tmp = tmp_path / "units" / "9" / ".v000002.json.999999.1.tmp"
    tmp.write_text("{half")
    again = CalibrationStore(tmp_path)
    assert again.clean_leftovers() == 1 and not tmp.exists()
    assert close_abandoned(again) == 1
    assert CalibrationStore(tmp_path).get(9, rec.version).push["status"] == "abandoned"


# ---- restarts and outliers ----------------------------------------------------------------------
def _block(seqs: list[int]) -> np.ndarray:
    b = np.zeros(len(seqs), dtype=SAMPLE_DTYPE)
    b["seq"] = np.asarray(seqs, dtype=np.int64) % (1 << 32)
    return b


def _kinds(out: list[tuple[str, np.ndarray]]) -> list[tuple[str, int]]:
    return [(k, int(b.size)) for k, b in out]


def test_one_far_sequence_number_is_an_outlier_not_a_restart() -> None:
    t = SeqTracker()
    assert _kinds(t.feed(_block(list(range(5000, 5100))))) == [("same", 100)]
    out = t.feed(_block([5100, 5101, 0x40000000, 5102, 5103]))
    assert _kinds(out) == [("same", 2), ("same", 2)] and t.outliers == 1 and t.restarts == 0


def test_a_real_restart_needs_several_samples_of_evidence() -> None:
    t = SeqTracker(confirm_n=32)
    t.feed(_block(list(range(5000, 5100))))
    assert t.feed(_block(list(range(0, 10)))) == [] and t.pending == 10  # held, not yet believed
    out = t.feed(_block(list(range(10, 40))))
    assert _kinds(out) == [("restart", 40)] and t.restarts == 1


def test_a_hello_makes_the_next_jump_the_new_numbering_at_once() -> None:
    t = SeqTracker()
    t.feed(_block(list(range(5000, 5100))))
    assert t.expect_restart() is None
    assert _kinds(t.feed(_block(list(range(0, 5))))) == [("same", 5)] and t.restarts == 0
    t2 = SeqTracker()
    t2.feed(_block(list(range(5000, 5100))))
    t2.feed(_block(list(range(0, 5))))  # seen before the HELLO was handled: held
    held = t2.expect_restart()
    assert held is not None and held.size == 5 and t2.restarts == 0


def test_a_forward_jump_confirmed_is_a_gap_in_the_same_session() -> None:
    t = SeqTracker(confirm_n=8)
    t.feed(_block(list(range(100))))
    out = t.feed(_block(list(range(50_000, 50_010))))
    assert _kinds(out) == [("same", 10)] and t.gaps == 1 and t.restarts == 0


# ---- the campaign, fast scenarios, real processes ----------------------------------------------
def _campaign() -> Any:
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "faults.py"
    spec = importlib.util.spec_from_file_location("gyrocal_faults_bench", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
@pytest.mark.parametrize("name", ["start_without_unit", "refused_pushes", "unit_silent", "pty_replug",
                                  "power_cycles"])
def test_fault_campaign_fast_scenarios_on_a_pty(name: str) -> None:
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    res = _campaign().run_one(name, "pty")
    assert res.up and res.agree and res.ok, res


def test_status_follows_the_unit_s_read_back_after_a_push(tmp_path: Path) -> None:
    """The push's own read-back updates unit_set: it said 'the unit holds no set' while the unit
    held the v1 just acked and read back (found by a unit built from docs/protocol.md alone)."""
    h = Harness.make(tmp_path)
    h.switch_on()
    h.run(90, until=_acked)
    s = h.session
    assert s is not None and _acked(h)
    unit_set = s.status()["unit_set"]
    assert unit_set["agree"] and unit_set["unit_version"] == 1, unit_set
    assert unit_set["store_status"] == "acked"


def test_a_read_back_that_differs_from_the_stored_version_is_one_warning(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    h = Harness.make(tmp_path)
    h.switch_on()
    h.run(90, until=_acked)
    s = h.session
    assert s is not None
    rec = h.store.get(4242, 1)
    other = tuple(tuple(c + 1e-4 for c in row) for row in rec.coefficients_dps)
    lie = CoeffReport(1, SEED000_ID, other)  # another tool wrote its own v1 into the unit
    with caplog.at_level("INFO", logger="gyrocal.session"):
        s.on_message(lie, h.now)
        s.on_message(lie, h.now)
    said = [r for r in caplog.records if "differs from the stored v1" in r.getMessage()]
    assert len(said) == 1 and said[0].levelname == "WARNING"
    assert not s.status()["unit_set"]["agree"]
    assert h.store.get(4242, 1).coefficients_dps == rec.coefficients_dps  # never "fixed"


def test_a_unit_measuring_its_own_boot_bias_holds_the_stored_set_not_a_foreign_one(tmp_path: Path) -> None:
    """ArduPilot's gyro calibration at each boot rewrites the constant of the held set. Its read-back
    (the whole cubic, float32) is the stored v1 with another constant: it agrees, and says the bias.
    Any other difference still disagrees, and a unit without own_boot_bias disagrees as before (every
    ArduPilot reboot was reported as a CRC disagreement: an integrator's audit)."""
    import numpy as np

    from gyrocal.daemon.reconcile import reconcile
    from gyrocal.protocol.messages import CoeffReport, coeff_set_crc
    from gyrocal.protocol.termsets import TEMP_POLY3_ID

    store = CalibrationStore(tmp_path)
    coeffs = [[0.01, 2e-4, -3e-6], [-0.02, 1e-4, 5e-6], [0.005, -3e-4, 1e-6]]
    rec = store.add(CalibrationRecord(serial=9, version=0, terms=["1", "temp", "temp^2"],
                                      coefficients_dps=coeffs, uncertainty_dps=[[None] * 3] * 3))
    store.update_push(9, rec.version, {"status": "acked"})

    def report(const_shift: float, t2_shift: float = 0.0) -> CoeffReport:
        cubic = np.zeros((3, 4))
        cubic[:, :3] = np.asarray(coeffs, dtype=np.float32)  # the autopilot's float32
        cubic[:, 0] += const_shift
        cubic[:, 2] += t2_shift
        return CoeffReport(rec.version, TEMP_POLY3_ID, cubic.tolist())

    def agree(msg: CoeffReport, own: bool) -> dict:
        crc = coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps)
        return reconcile(store, 9, msg.version, crc, msg, own_boot_bias=own).as_dict()

    boot = agree(report(0.002), own=True)
    assert boot["agree"] and boot["own_bias_dph"] == [7.2, 7.2, 7.2] and "boot" in boot["note"]
    assert not agree(report(0.002, t2_shift=1e-6), own=True)["agree"]  # a temperature term moved
    assert not agree(report(0.002), own=False)["agree"]
    # version 0 from an autopilot carries what it subtracts: a set, just not one of ours
    foreign = reconcile(store, 9, 0, None, CoeffReport(0, TEMP_POLY3_ID, [[1e-3, 0, 0, 0]] * 3))
    assert "did not write" in foreign.note
    assert reconcile(store, 9, 0, None, CoeffReport(0, TEMP_POLY3_ID, [[0.0] * 4] * 3)).note == (
        "the unit holds no set (version 0)")
    # a push cut short (a reboot right after its ENABLE = 1): the record says 'abandoned', the unit
    # holds the set with its boot's constant; it is the set, applied with its ack lost
    rec = store.add(CalibrationRecord(serial=9, version=0, terms=["1", "temp", "temp^2"],
                                      coefficients_dps=coeffs, uncertainty_dps=[[None] * 3] * 3,
                                      push={"status": "abandoned"}))
    cut = agree(report(0.002), own=True)
    assert cut["agree"] and cut["store_status"] == "applied_ack_lost" and cut["own_bias_dph"] == [7.2] * 3
    assert store.get(9, rec.version).push["status"] == "applied_ack_lost"


def test_a_write_into_a_link_the_session_said_is_down_is_not_warned_again(caplog: Any) -> None:
    """The session's send says False for a link it has already logged as down (one WARNING per
    outage): the push's 'the write could not be sent' is then INFO. One cable pull mid-push gave this
    fact twice at WARNING (an integrator's fault campaign, F3). A send that raises, which nobody has
    said, stays a WARNING."""
    import logging

    from gyrocal.daemon.push import PushTransaction
    from gyrocal.protocol.messages import CoeffWrite
    from gyrocal.protocol.termsets import terms_id

    terms = ["1", "gx", "gy", "gz"]
    write = CoeffWrite(8, terms_id(terms), np.full((3, 4), 0.001))
    sends: list[Any] = []

    def down(msg: Any) -> bool:
        sends.append(msg)
        return len(sends) == 1  # the first write left; the cable was pulled before its ack

    for send, warned in ((down, 0), (_unplugged, 3)):
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="gyrocal.push"):
            t, p = 0.0, PushTransaction(write, send, 0.0)
            while not p.finished and t < 60.0:
                t += 0.1
                p.tick(t)
        said = [r for r in caplog.records if "could not be sent" in r.getMessage()]
        assert p.result is not None and p.result.status in ("timeout", "link_down")
        assert sum(r.levelno >= logging.WARNING for r in said) == warned, [r.getMessage() for r in said]
        assert len(said) == (2 if send is down else 3)


def test_a_link_said_lost_mid_push_is_not_said_again_by_the_push_or_the_session(
        tmp_path: Path, caplog: Any) -> None:
    """After the engine's one WARNING for a lost link (session.link_lost), the push's missing ack and
    the session's failed sends are its consequences, at INFO; the push still ends in a record. One
    cable pull mid-push gave the loss, 'no ack within 1.0 s' and 'CoeffWrite not sent' as three
    WARNINGs (an integrator's fault campaign, F3)."""
    import logging

    h = Harness.make(tmp_path, faults=Faults(drop_acks=100))
    h.switch_on()
    h.run(90, until=lambda h: h.session is not None and h.session.state is State.PUSHING)
    s = h.session

    with caplog.at_level(logging.INFO):
        s.link_lost()
        s.send = _unplugged
        h.run(30, until=_pushed)
    said = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert any("no ack within" in m for _, m in said) and any("could not be sent" in m for _, m in said), said
    assert not [m for lv, m in said if lv >= logging.WARNING and ("no ack" in m or "not sent" in m)], said
    assert s.last_push["status"] in ("link_down", "timeout")
    assert h.store.get(4242, s.last_push["version"]).push["status"] == s.last_push["status"]


def test_an_ack_that_comes_in_the_back_off_after_its_timeout_is_taken() -> None:
    """A unit that acks in 0.8 s, after a reload cut push.ack_timeout_s to 0.5: each ack came in the
    back-off before the next attempt and was not taken. v9 was written 5 times, 5 acks came, and the
    push ended 'timeout' (an integrator's campaign, rc33 G7). protocol.md: a later answer is not
    lost. The late ack is taken and the set read back; only an ack of this very set (version and
    CRC) is."""
    from gyrocal.daemon.push import PushPhase, PushTransaction
    from gyrocal.protocol.messages import CoeffAck, CoeffRead, CoeffReport, CoeffWrite, coeff_set_crc
    from gyrocal.protocol.termsets import terms_id

    terms = ["1", "gx", "gy", "gz"]
    write = CoeffWrite(9, terms_id(terms), np.full((3, 4), 0.001))
    crc = coeff_set_crc(write.version, write.terms_id, write.coeffs_dps)
    for late in (CoeffAck(9, crc ^ 1), CoeffAck(8, crc), CoeffAck(9, crc)):
        sent: list[Any] = []
        p = PushTransaction(write, sent.append, 0.0, ack_timeout_s=0.5, retries=5)
        t = 0.0
        while t < 0.79:
            t += 0.01
            p.tick(t)
        assert p.phase is PushPhase.BACKOFF and p.attempts == 1
        taken = p.on_message(late, t)
        if late.crc != crc or late.version != 9:
            assert not taken and p.phase is PushPhase.BACKOFF  # not this set's ack: the push goes on
            continue
        assert taken and p.phase is PushPhase.WAIT_READBACK and p.acked_crc == crc
        assert isinstance(sent[-1], CoeffRead) and sum(isinstance(m, CoeffWrite) for m in sent) == 1
        p.on_message(CoeffReport(9, write.terms_id, write.coeffs_dps), t + 0.1)
        assert p.result is not None and p.result.status == "acked" and p.result.readback_ok


def test_a_read_the_link_did_not_take_is_asked_again_soon_after_the_link_returns(tmp_path: Path) -> None:
    """The unit's set unknown (a read-back due) while the CAN bus is down for 10 s, samples flowing
    again at once when it returns: the COEFF_READs that could not be sent doubled the back-off as if
    the unit had not answered, and the set was read back 7 s after the samples returned, none of them
    learnt meanwhile (an integrator's campaign, rc33 G4). A read the link did not take is asked again
    after push.ack_timeout_s (1 s)."""
    h = Harness.make(tmp_path)
    h.switch_on()
    h.run(2)
    s = h.session
    assert s is not None and s.applied is not None
    send = s.send
    s.send = _unplugged
    s._forget_set()
    s.request_read(h.now)
    h.run(10)
    assert s.applied is None and s.send_failures >= 8  # asked about once a second, never answered
    s.send = send  # the bus is back
    h.run(1.5)
    assert s.applied is not None and s._read_asks <= 1
