"""Unit capabilities (daemon/capabilities.py): the daemon learns the full model, pushes what the unit
can hold, and keeps the rest (and a reboot-needed push) in the store and in status."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gyrocal.daemon.capabilities import PROTOCOL, UnitCapabilities, project
from gyrocal.daemon.cli_control import format_status
from gyrocal.daemon.learner import make_learner
from gyrocal.daemon.session import Session
from gyrocal.daemon.stillness import StillDetector
from gyrocal.model.terms import SEED000_TERMS, TermSpec
from gyrocal.protocol.termsets import TEMP_POLY3_TERMS
from tests.daemon_harness import RATE_HZ, Harness

AUTOPILOT = UnitCapabilities("mavlink px4", tuple(TEMP_POLY3_TERMS[:k] for k in (4, 3, 2)), 4, True)


def test_the_largest_held_term_set_is_chosen_and_the_protocol_holds_any_set() -> None:
    names = ["1", "temp", "temp^2", "gz"]
    assert AUTOPILOT.held_subset(names) == ("1", "temp", "temp^2")
    assert AUTOPILOT.held_subset(["gx", "temp"]) is None  # no constant: nothing it can hold
    assert not AUTOPILOT.holds(names) and AUTOPILOT.holds(("1", "temp"))
    assert PROTOCOL.held_subset(names) == tuple(names)
    assert PROTOCOL.held_subset([f"t{i}" for i in range(22)]) is None  # > 21 terms


def test_projection_moves_a_gravity_term_into_the_constant_at_a_unit_that_sits_level() -> None:
    """An autopilot at one attitude: gz is 1 at every pose, so the unit's constant takes it exactly;
    a term the poses do not determine apart (temp^2 over one temperature) is left as learnt."""
    names = ["1", "temp", "temp^2", "gz"]
    spec = TermSpec.parse(names)
    rng = np.random.default_rng(3)
    c = rng.normal(0, 0.01, (3, 4))
    temps = np.linspace(20, 50, 12)
    cols = {"temp": temps, "ax": np.zeros(12), "ay": np.zeros(12), "az": np.ones(12), "t": np.zeros(12)}
    phi = spec.design(cols)
    p = project(names, c, ("1", "temp", "temp^2"), phi)
    np.testing.assert_allclose(p.held_dps[:, 0], c[:, 0] + c[:, 3], atol=1e-12)
    np.testing.assert_allclose(p.held_dps[:, 1:], c[:, 1:3], atol=1e-12)
    assert np.all(p.left_poses_dps < 1e-12)  # nothing left at the unit's poses
    # tilted poses: gz is no longer constant; what the held terms cannot follow is left and reported
    cols["az"] = np.cos(np.linspace(0, 1.2, 12))
    p = project(names, c, ("1", "temp", "temp^2"), spec.design(cols))
    drift_full = spec.design(cols) @ c.T
    drift_unit = spec.design(cols) @ p.embedded_dps.T
    left = np.sqrt(np.mean((drift_full - drift_unit) ** 2, axis=0))
    np.testing.assert_allclose(p.left_poses_dps, left, rtol=1e-9)
    assert np.all(left <= np.sqrt(np.mean((spec.design(cols)[:, 3:] @ c[:, 3:].T) ** 2, axis=0)) + 1e-15)
    rec = p.record(names)
    assert rec["terms"] == names and rec["held_terms"] == ["1", "temp", "temp^2"]
    # the host's part plus the unit's part is the learnt set
    np.testing.assert_allclose(np.array(rec["coefficients_dps"]) + p.embedded_dps, c, atol=1e-15)


def test_a_unit_that_holds_less_gets_its_part_and_the_store_keeps_the_rest(tmp_path: Path) -> None:
    """Learn seed 000 + temp; the unit holds seed 000 only and applies a push after a reboot."""
    from gyrocal.protocol import termsets

    terms = [*SEED000_TERMS, "temp"]
    termsets.register(terms)
    caps = UnitCapabilities("test unit", (tuple(SEED000_TERMS),), 21, reboot_required=True)
    h = Harness.make(tmp_path, **{"estimator.terms": terms})
    hello = h.unit.power_on()
    h.detector = StillDetector.for_rate(RATE_HZ, h.cfg.still)
    h.session = Session(h.cfg, hello[0], make_learner(h.cfg, None, RATE_HZ), h.store, h.send, h.now,
                        RATE_HZ, caps=caps)
    h.run(120, until=lambda h: bool(h.session and h.session.last_push))
    s = h.session
    assert s.last_push.get("status") == "acked", s.reason
    assert h.unit.status()["applied_terms"] == list(SEED000_TERMS)
    rec = h.store.latest(4242)
    assert rec is not None and rec.terms == list(SEED000_TERMS)
    assert rec.push["reboot_required"] is True
    rem = rec.host_remainder
    assert rem["terms"] == terms and rem["held_terms"] == list(SEED000_TERMS)
    c = np.array(rem["coefficients_dps"])
    assert np.any(c[:, terms.index("temp")] != 0)  # the temperature slope the unit cannot hold
    assert all(rem["drift_left_poses_dph"][a] >= 0 for a in "xyz")
    st = s.status()
    assert st["reboot_needed"]["version"] == rec.version and st["host_remainder"] == rem
    text = format_status(st, 100)
    assert "REBOOT NEEDED" in text and f"v{rec.version}: the unit (test unit)" in text
    assert "host_remainder" in text
    # the unit compensates what it holds: its drift is cut even without the host's part
    u = h.unit.status()
    for a in "xyz":
        assert u["drift_rms_compensated_dps"][a] * 3 <= u["drift_rms_raw_dps"][a], (a, u)
    # the next switch-on warm-starts from the learnt set behind the projected record (held part +
    # host remainder), not cold: its learner has the prior, and its first set is the bias stage's
    learnt = c.copy()  # the remainder, plus the held part in the learnt term order
    learnt[:, [terms.index(n) for n in rec.terms]] += np.array(rec.coefficients_dps)
    assert np.allclose(learnt, s.learner.coefficients, rtol=0.2, atol=2e-4)  # what was learnt
    hello = h.unit.power_on()
    learner = make_learner(h.cfg, rec, RATE_HZ)
    assert learner.has_prior and np.allclose(learner.prior, learnt, rtol=1e-12, atol=1e-15)
    assert learner.prior_info is not None  # the temperature term's information carries over too
    h.detector = StillDetector.for_rate(RATE_HZ, h.cfg.still)
    h.session = Session(h.cfg, hello[0], learner, h.store, h.send, h.now, RATE_HZ,
                        warm_started_from=rec.version, caps=caps)
    h.run(60, until=lambda h: bool(h.session and h.session.last_push.get("status") == "acked"))
    s2 = h.session
    assert s2.last_push.get("status") == "acked", s2.reason
    rec2 = h.store.latest(4242)
    assert rec2.version == rec.version + 1 and rec2.terms == list(SEED000_TERMS)
    assert rec2.stats["predicted_drift_dph"]["stage"] == "bias", rec2.stats["predicted_drift_dph"]
    assert rec2.host_remainder["terms"] == terms  # the learnt rest still kept for the host


def test_a_set_held_at_a_hello_that_needs_a_reboot_says_so(tmp_path: Path) -> None:
    """A PX4 that booted with TC_G_ENABLE 0 and holds v1 (the link wrote it back after a push cut by
    a reboot): status said "applied v1, as the store says" and no reboot_needed, while that boot
    applied nothing (an integrator's audit)."""
    from gyrocal.protocol.messages import CoeffReport
    from gyrocal.protocol.termsets import terms_id

    caps = UnitCapabilities("test unit", (tuple(SEED000_TERMS),), 21, reboot_required=True)
    h = Harness.make(tmp_path)
    hello = h.unit.power_on()
    s = Session(h.cfg, hello[0], make_learner(h.cfg, None, RATE_HZ), h.store, h.send, h.now, RATE_HZ,
                caps=caps)
    coeffs = np.full((3, len(SEED000_TERMS)), 1e-3)
    s.on_message(CoeffReport(1, terms_id(list(SEED000_TERMS)), coeffs.tolist()), 0.0)
    assert s.reboot_needed is not None and s.reboot_needed["version"] == 1
    assert "REBOOT NEEDED" in format_status(s.status(), 100)
