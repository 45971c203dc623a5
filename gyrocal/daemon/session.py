"""One calibration session of one unit: from its switch-on to the pushed, monitored set.

    WAIT_HELLO -> COLLECTING -> CONVERGED -> VALIDATING -> PUSHING -> APPLIED -> MONITORING

- COLLECTING: still samples train the estimator, except held-out blocks (see blocks.py).
- CONVERGED: the estimator says so and every direction the data must determine is determined.
  The push gate then asks what the user cares about: the drift the set is predicted to leave
  (standard error of the prediction, learner.py) over the unit's poses must be below
  1/``push.min_cut`` of the drift it removes, on every axis, or below ``push.target_drift_dph``.
  That figure (``left``) mixes the figure over the poses seen with the worse of it and the figure
  over the sphere of gravity directions, in the share of the unit's rests at poses not seen yet
  (Good-Turing, ``unseen_share``). The sphere counts because the unit is judged at poses the
  daemon may not have seen yet: gated on the poses seen alone, an independent unit's first push
  cut its worst axis only 5-21x over its 24 poses (27-104x with the sphere). While every rest finds
  a new pose the share is 1 and the sphere decides; once the unit keeps coming back to the poses
  seen, they do.
- Staged calibration: a warm-started session (a stored set) first pushes a bias-only set, from its
  first still second, validated on the blocks seen; the full set follows once the data supports it.
- VALIDATING: the new set must lower the held-out residual against the set the unit holds now, by
  ``validation.min_improvement``; otherwise nothing is pushed and the reason is logged. On a unit
  whose bias wanders (a ``kf`` spec), a first set passes on a significant paired gain instead
  (``WANDER_GAIN_Z``): the wander is in every block and no set removes it (refine.py's floor).
- PUSHING: push.py's transaction (write, matching ack, read back, retries).
- APPLIED -> MONITORING: keep learning; a drift alarm when the pushed set's residual grows. The
  residual is raw - C_applied @ phi over the monitor blocks, so blocks of samples the unit sent
  before it applied the set (the still detector decides them late) are judged with the new set too.

The unit compensates its own output with the set it holds, so the daemon reconstructs the raw rate
as ``raw = out + C_applied @ phi`` before learning: the estimator always learns the unit's total
drift, and a new set replaces the old one rather than stacking on it. The applied set is read from
the unit (COEFF_READ) at the start of every session, never assumed.

Recovery rules (issue 8: a fault becomes a state, a record and one log line; never an exit, never a
stuck state):

- Reading the unit's set (COEFF_READ, at the start, after a reconnect, after a failed push): asked
  again with a back-off that doubles from ``push.ack_timeout_s`` to ``READ_BACKOFF_MAX_S``; after
  ``READ_WARN_AFTER`` unanswered asks, one WARNING; an ask the link could not send does not count,
  and is made again after ``push.ack_timeout_s``. Until a valid report comes, the session counts
  samples but does not learn (raw = out + applied set needs the applied set), and status says so.
- A refused report (NaN/Inf, absurd values, a term set this daemon does not know; push.check_report)
  is counted (``refused_reports``), logged once, and asked for again with the same back-off.
- PUSHING always ends: push.py's transaction times out into a result (acked, nak, timeout,
  link_down, readback_*). A push refused before it starts (push.check_set, a link that is down)
  never enters PUSHING: the record gets push status 'refused' with the reason, the session stays
  where it was. After any failed push the unit's set is read back (the unit applies a set whole or
  not at all), and the reconciliation (reconcile.py) decides what the unit holds.
- A transient failure (BUSY, no ack, link down, no read-back) is retried as the SAME record (same
  version, same coefficients) after a back-off of ``RETRY_BACKOFF_S`` doubling to
  ``RETRY_BACKOFF_MAX_S``: a NAK storm never mints new versions. A final NAK (unknown terms, out of
  range) drops the set; the next validation may propose a new one.
- Store failures (disk full, read-only): a validated set that cannot be recorded is NOT pushed
  (never a unit set the store does not know); status says "store unavailable: <reason>", and the
  validation is tried again after ``STORE_RETRY_S``. A push result that cannot be written is kept
  in memory and written at the next chance (``unrecorded``).
- Every send goes through ``_send``: a link failure is counted and logged once per outage, and the
  state's own timeout takes it from there.

Pure logic: the engine owns threads and I/O, and hands in ``send``, ``now`` and the store.
"""

from __future__ import annotations

import enum
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from gyrocal.daemon import refine
from gyrocal.daemon.blocks import BlockAccumulator, BlockWindow
from gyrocal.daemon.capabilities import PROTOCOL, Projection, UnitCapabilities, project
from gyrocal.daemon.earth_track import EarthTrack
from gyrocal.daemon.learner import Learner, temp_indices
from gyrocal.daemon.poses import PoseLog
from gyrocal.daemon.push import PushPhase, PushTransaction, check_report, check_set
from gyrocal.daemon.reconcile import record_crc
from gyrocal.daemon.session_recovery import RecoveryMixin
from gyrocal.daemon.stepcheck import find_step
from gyrocal.daemon.store import APPLIED_STATUSES, CalibrationRecord, utc_now
from gyrocal.model.earth import vertical_earth_rate_dps
from gyrocal.model.prep import block_terms
from gyrocal.model.terms import TermSpec
from gyrocal.protocol.messages import (
    SEQ_MODULO,
    CoeffAck,
    CoeffReport,
    CoeffWrite,
    Hello,
    NakReason,
    coeff_set_crc,
)
from gyrocal.protocol.termsets import TempRate, names_for, terms_id

log = logging.getLogger("gyrocal.session")


class State(enum.Enum):
    WAIT_HELLO = "WAIT_HELLO"
    COLLECTING = "COLLECTING"
    CONVERGED = "CONVERGED"
    VALIDATING = "VALIDATING"
    PUSHING = "PUSHING"
    APPLIED = "APPLIED"
    MONITORING = "MONITORING"


@dataclass
class AppliedSet:
    """The coefficient set the unit holds, as it reported it."""

    version: int
    terms_id: int
    names: tuple[str, ...]
    coeffs_dps: np.ndarray  # (3, P) deg/s per term unit

    def same_as(self, other: AppliedSet) -> bool:
        """The same set: version, terms and coefficients."""
        return (self.version == other.version and self.terms_id == other.terms_id
                and np.shape(self.coeffs_dps) == np.shape(other.coeffs_dps)
                and bool(np.array_equal(self.coeffs_dps, other.coeffs_dps)))

    def beyond_constant(self) -> bool:
        """Whether a term other than the constant has a non-zero coefficient (a curve, not a bias)."""
        other = [k for k, n in enumerate(self.names) if n != "1"]
        return bool(np.any(self.coeffs_dps[:, other])) if other else False

    def uses(self, atom: str) -> bool:
        """Whether a term with a non-zero coefficient needs ``atom`` (``dtemp``, ``temp``, ``t_on``)."""
        if not self.names:
            return False
        terms = TermSpec.parse(self.names).terms
        return any(atom in term.atoms and bool(np.any(self.coeffs_dps[:, k])) for k, term in enumerate(terms))

    def compensation(self, cols: dict[str, np.ndarray], phi: np.ndarray | None = None) -> np.ndarray:
        """What the unit subtracts from its output, (N, 3) [deg/s]; ``phi``: these cols' terms, if known."""
        if not self.names or not np.any(self.coeffs_dps):
            return np.zeros((cols["t"].shape[0], 3))
        # gravity terms from a/|a|, as the unit computes them (docs/protocol.md, section 6)
        if phi is None:
            phi = block_terms(TermSpec.parse(self.names), cols)
        return phi @ self.coeffs_dps.T

    @classmethod
    def from_report(cls, msg: CoeffReport) -> AppliedSet:
        coeffs = np.asarray(msg.coeffs_dps, dtype=np.float64).reshape(3, -1)
        names = names_for(msg.terms_id) or ()
        if coeffs.size and len(names) != coeffs.shape[1]:
            names = ()
        return cls(msg.version, msg.terms_id, tuple(names), coeffs)


def finite_or_none(a: np.ndarray) -> list[Any]:
    """A nested list for JSON, with NaN and Inf (an undetermined coefficient) as None."""
    return [[float(v) if np.isfinite(v) else None for v in row] for row in np.atleast_2d(a)]


def same_boot(prior: CalibrationRecord | None, hello: Hello) -> dict[str, Any] | None:
    """``{"version", "time_s", "stage"}`` when the stored set the unit held last was acked in the boot
    ``hello`` names, at unit time ``time_s`` [s]; ``stage``: "bias" for a bias-only set, else what its
    validation said (None for an operator's file); ``push``: the record's push result; ``operator``:
    what an operator's push of it was ("a rollback"), else None. None otherwise (and for records older
    than that)."""
    unit = (prior.push.get("unit") or {}) if prior is not None else {}
    t = unit.get("time_s")
    if unit.get("boot_count") != hello.boot_count or not isinstance(t, int | float) or not np.isfinite(t):
        return None
    stage = (prior.stats.get("validation") or {}).get("stage")
    return {"version": prior.version, "time_s": float(t), "stage": stage, "push": dict(prior.push),
            "operator": prior.push.get("operator")}


DPH = 3600.0
SPHERE_G = (lambda v: v / np.linalg.norm(v, axis=1)[:, None])(np.random.default_rng(7).normal(size=(256, 3)))
"""Directions [g] over which the drift a set leaves is predicted (fixed, seeded)."""
FIRST_SAMPLE_MAX_S = 60.0
"""[s] A unit's first sample after switch-on (seq 0) stamped later than this has a clock that does not
count from switch-on (an uptime, a clock kept across power cycles): t_on is that unit time, so one
WARNING says that its warm-up terms cannot fit."""
WANDER_GAIN_Z = 3.0
"""A first set on a unit whose bias wanders passes validation when its held-out gain is this many
standard errors, paired per block (one-sided p about 0.001 for independent blocks; the blocks of one
rest are alike, so it is kept strict)."""
PREDICTED_KEYS = ("left", "expected", "bound", "left_poses", "left_sphere", "removes")
"""The per-axis figures [deg/s] of a prediction (learner.py), shown and recorded in deg/h."""
HeldInfo = tuple[np.ndarray | None, tuple[float, float] | None, np.ndarray | None]
"""The held set's record: predicted drift left [deg/s] (3,), temperature range [degC], kept axes."""


class Session(RecoveryMixin):
    """The state machine of one switch-on. See the module docstring."""

    CHECK_EVERY_S = 0.25
    MAX_POSES = 64
    SLOW_WRITE_S = 1.0
    """A record write longer than this [s] defers its push until the samples of its time are read."""
    BIAS_MIN_S = 1.0
    """Seconds of still samples before a bias-only set may be pushed."""
    CONTRADICTED_MAX = 3
    """UNKNOWN_TERMS NAKs for the term set the unit reports holding that are tried again, not final."""
    STEADY_S = 60.0
    STEADY_BAND_C = 0.5
    """A cold start learns a constant alone once its data has stopped adding directions for STEADY_S
    [s] of unit time (the rank unchanged; with temperature terms, the still samples' temperature also
    within +-STEADY_BAND_C [degC]) and the unit holds no set beyond a constant (learner.py, "A cold
    start that stops learning"): a heated IMU, and a unit mounted at one pose, were never calibrated."""
    HOLD_STALL_S = 30.0
    """A cold start whose rank has not grown for this long [s of unit time], short of the structural
    rank, holds at 0 the terms its data cannot separate, when every other term is determined
    (model/held_zero.py): the built-in set 0x549E stops at rank 12 of 13 on a whole warm-up tumble, and
    such a unit was never calibrated (a fleet engineer's year: 18 switch-ons with no set)."""
    BIAS_MIN_CUT = 3.0
    """The bias stage pushes once the new bias is predicted to cut every axis's present drift this many
    times (or leave less than ``push.target_drift_dph``): it is a first step, which the full set refines.
    The first push of a cold start and every full set use ``push.min_cut`` (20)."""

    def __init__(
        self, cfg: Any, hello: Hello, learner: Learner, store: Any, send: Callable[[Any], None],
        now: float, rate_hz: float, warm_started_from: int | None = None,
        caps: UnitCapabilities = PROTOCOL, same_boot: dict[str, Any] | None = None,
    ) -> None:
        self.cfg = cfg
        self.caps = caps  # what the unit can hold: a set is projected onto it before a push
        self.reboot_needed: dict[str, Any] | None = None  # an acked set the unit applies after a reboot
        self._projection: Projection | None = None  # the split of the set being validated/pushed
        self.host_remainder: dict[str, Any] | None = None  # of the last acked set, for status
        self.next_set_waits: str | None = None  # while monitoring: why no further set is pushed yet
        self._refused_why = ""  # the last validation's refusal, for next_set_waits
        self.hello = hello
        self.learner = learner
        self.store = store
        self.send = send
        self.names = list(learner.names)
        self.spec = TermSpec.parse(self.names)
        self.terms_id = terms_id(self.names)
        self.warm_started_from = warm_started_from
        # the warm start's push was acked in this boot ({"version", "time_s"}): if the unit's clock went
        # on from it, this daemon restarted within the switch-on it calibrated (see _check_same_boot)
        self._same_boot = same_boot
        self.resumed_from: int | None = None
        self.state = State.COLLECTING
        self.applied: AppliedSet | None = None
        self.started = now
        self.rate_hz = rate_hz
        self._new_blocks()
        monitor_blocks = int(cfg.monitor["window_s"] / cfg.validation["block_s"])
        self.monitor = BlockWindow(max(4, monitor_blocks))
        self.push: PushTransaction | None = None
        self._pending: tuple[list[str], np.ndarray] = ([], np.zeros((3, 0)))
        self._switch: tuple[AppliedSet, int | None] | None = None  # acked set, seq before the ack
        self.validated_rms: np.ndarray | None = None
        self._watch_rms: np.ndarray | None = None  # the alarm reference before a push (_watch_held)
        self.last_validation: dict[str, Any] = {}
        self.last_push: dict[str, Any] = {}
        self.alarm = False
        self.alarm_beyond_range = False  # the residual is over the alarm limit only beyond the held range
        self.reason = "reading the set the unit holds (COEFF_READ)"
        self.samples = 0
        self.still_samples = 0
        self.pose_log = PoseLog(max_poses=self.MAX_POSES)  # distinct poses seen, and visits to each
        # the temperature range [degC] of this session's still samples (None: the model has no temp)
        self._has_temp = "temp" in self.spec.atoms
        self.temp_seen: tuple[float, float] | None = None
        self._held_cache: dict[int, HeldInfo] = {}
        self._gate_result: refine.GateResult | None = None
        self._keep_held: np.ndarray | None = None  # (3,) bool: bias-stage axes that keep the held bias
        self._bias_partial = False  # a bias stage pushed on some axes only: the others when they gain
        self._bias_said = ""  # the last partial bias stage's line, said once
        self._refusal_logged: set[int] = set()
        self._context: dict[str, float] = {}  # latest non-gravity inputs (temp, t_on, ...)
        self.prediction: dict[str, Any] = {}
        self._bias_pushed = False
        self._push_prediction: dict[str, Any] = {}
        self._trate = TempRate()  # dtemp by the unit's own rule (protocol.md, section 6)
        lat = cfg.site["latitude_deg"]  # [deg]: the Earth's rotation is true rate, not drift
        self.earth = None if lat is None else EarthTrack(lat, len(self.names))
        self._next_check = now
        self._next_validation_at = 0
        self._validated_at = 0  # learner samples at the last validation
        self._peak_trate = 0.0  # the fastest |dT/dt| [degC/s] seen this session (refine.settled)
        self._steady_from: tuple[float, float] | None = None  # (unit time [s], temp [degC]) of the band
        self._steady_s = 0.0  # how long [s] the temperature has stayed in that band (STEADY_S)
        self._rank_since: tuple[int, float] = (-1, float("nan"))  # (rank, unit time [s] it was reached)
        self._range_pushed: tuple[float, float] | None = None  # temp_seen [degC] at the last full set
        self._rank_validated = 0  # the learner's rank at the last validation (an early one when it grows)
        self._relearned_at = float("-inf")  # unit time [s] learning last started again on an alarm
        self._relearned_from: int | None = None  # the version the unit held then
        self._relearning = False  # ... and its bias stage is due (_relearn_after_alarm)
        self._relearn_stages: set[int] = set()  # versions of the bias stages pushed after such a restart
        self._alarm_kept: set[int] = set()  # ... whose alarm came back and was said once
        # bias steps found in the data being learnt from (_step_found): status and each record say them
        self.bias_steps: list[dict[str, Any]] = []
        self._held_said: list[str] = []  # the terms held at 0 that the log has named (HOLD_STALL_S)
        self._t_last = float("nan")  # the newest sample's time stamp [s], the unit's clock
        self.unit_clock_s = float("nan")  # the newest time stamp heard [s], decided or not (heard)
        # (from, to) unit time [s]: samples whose set is not known, from a push's first write to its ack,
        # or to the read of the unit's set after a push that failed (to None until then)
        self._blind: list[float | None] | None = None
        self.blind_samples = 0  # samples neither learnt, held out nor monitored for that
        self.inexact_samples = 0  # samples neither learnt nor held out: the unit's dtemp not yet known
        self._inexact_said = False  # the stretch of inexact samples now running has been logged
        self._unknown_terms: dict[int, str] = {}  # terms_id the unit NAKed UNKNOWN_TERMS -> the reason
        self._contradicted = 0  # UNKNOWN_TERMS NAKs for a term set the unit reports holding
        self._set_before_read: AppliedSet | None = None  # the unit's set before it was read again
        self.stray_acks = 0  # acks no push waited for, of no stored set (bus garbage, another host)
        self._said_converged = False  # the "estimator converged" line of this stretch was logged
        self._held_has_north = False  # the held set was pushed before north was found (_north_found)
        self.unconfirmed: str | None = None  # why the unit's identity is a guess (no HELLO yet), or None
        # why nothing is pushed on the daemon's own account: an operator pushed a set (hold_for_operator)
        self.operator_hold: str | None = None
        self._operator_push: tuple[int, str] | None = None  # (version, what) of the operator's push
        self._range_naks = 0  # new sets NAKed OUT_OF_RANGE in a row this session
        self.range_hold: str | None = None  # why no more sets are pushed this session (RANGE_NAKS_MAX)
        self._read_deadline = now
        self._read_asks = 0
        self.refused_reports = 0
        self.send_failures = 0
        self._link_warned = False
        self.store_error: str | None = getattr(store, "read_only", None)  # read-only since start
        self._store_retry_at = 0.0
        self.unrecorded: list[tuple[int, dict[str, Any]]] = []  # push results the store could not take
        self.agreement: dict[str, Any] = {}
        self._retry: dict[str, Any] | None = None  # a transiently failed push to send again, same version
        self._push_due: dict[str, Any] | None = None  # a set recorded by a slow store, pushed when caught up
        self._retry_round = 0
        self.request_read(now)

    # -- messages from the unit -------------------------------------------------------------
    def on_message(self, msg: Any, now: float, last_seq: int | None = None) -> None:
        """A unit message; ``last_seq`` is the seq of the sample just before it on the wire."""
        if self.push is not None:
            # an ack in the back-off after an attempt's timeout is taken too (push.py): the switch to
            # the new set is made for it as for one in time. Without it, the session took a late ack,
            # said "v8 applied and read back", and kept v7 as the unit's set: 11,319 of 11,695 samples
            # were then skipped as of an unknown set, and nothing was monitored (rc35 N0)
            waiting_ack = self.push.phase in (PushPhase.WAIT_ACK, PushPhase.BACKOFF)
            if self.push.on_message(msg, now):
                if waiting_ack and self.push.phase is PushPhase.WAIT_READBACK:
                    # acked: the unit compensates with the new set from the sample after the ack on
                    names, coeffs = self._pending
                    new = AppliedSet(self.push.write.version, terms_id(names), tuple(names), coeffs)
                    self._switch = (new, last_seq)
                    self._end_blind()
                self._after_push(now)
                if self.push is None and isinstance(msg, CoeffReport) and check_report(msg) is None:
                    # the push's read-back is a read of the unit's set like any other: the store and
                    # status's unit_set follow it (it said "no set" after v1 was acked and read back)
                    self._reconcile(msg)
                return
        if isinstance(msg, CoeffReport):
            self.on_report(msg, now)
        elif isinstance(msg, CoeffAck) and self.push is None and self.applied is not None \
                and self._stored_set_acked(msg):
            # an ack no push waits for, of a set this store wrote: the unit applied it late (after this
            # daemon restarted mid-push, or after the push had timed out), so its set is not the one
            # learning assumes. It was ignored, and status said "the unit holds v1, as the store says"
            # while the unit held v2 (an integrator's audit): read the set again, learning paused until
            # it answers. An ack of a set the store does not know (bus garbage) is only counted
            log.warning("unit %s: an ack of v%d arrived with no push waiting for it (the unit applied a "
                        "set late?): reading the unit's set again", self.hello.serial, msg.version)
            self._forget_set()
            self._read_asks = 0
            self.request_read(now)

    def _end_blind(self) -> None:
        """The unit's set is known again from the newest sample heard on (an ack, a read)."""
        if self._blind is not None and self._blind[1] is None:
            self._blind[1] = self.unit_clock_s

    def _forget_set(self) -> None:
        """The unit's set is unknown until it is read again (kept aside to see whether it changed)."""
        if self.applied is not None:
            self._set_before_read = self.applied
        self.applied, self._switch = None, None

    def _stored_set_acked(self, ack: CoeffAck) -> bool:
        """Whether ``ack`` names a stored version of this unit by its CRC (else it is counted)."""
        try:
            rec = self.store.get(self.hello.serial, ack.version) if ack.version else None
        except Exception:  # the store is advisory here
            rec = None
        if rec is not None and record_crc(rec) == ack.crc:
            return True
        self.stray_acks += 1
        return False

    def _being_pushed(self, msg: CoeffReport) -> bool:
        """Whether ``msg`` reports the very set of the push under way (version, terms and CRC)."""
        p = self.push
        return p is not None and p.write.version == msg.version and p.write.terms_id == msg.terms_id \
            and p.expected_crc == coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps)

    def on_report(self, msg: CoeffReport, now: float) -> None:
        """The unit's set: checked, reconciled with the store, then the base of learning."""
        why = check_report(msg)
        if why is not None:
            self.refused_reports += 1
            if self.refused_reports == 1 or self.refused_reports % 100 == 0:
                log.warning("unit %s: COEFF_REPORT v%d refused (%s; %d so far); asking again",
                            self.hello.serial, msg.version, why, self.refused_reports)
            if self.applied is None:
                self.reason = f"the unit's set cannot be used ({why}); asking again, not learning meanwhile"
            return
        applied = AppliedSet.from_report(msg)
        before, self._set_before_read = self._set_before_read, None
        if self.applied is None and before is not None and not before.same_as(applied):
            # the set changed at a point the daemon did not see (an ack lost, a late ack, an outage):
            # the monitor's blocks around it were rebuilt with the wrong set, and a drift alarm at
            # 52 / 45 / 26 deg/h followed while the unit was at 0.7 / 0.45 / 0.9 (an integrator's
            # fault campaign). The monitor starts again on the set the unit reports
            self._watch_afresh()
            log.info("unit %s: it holds v%d where v%d was: the drift monitor starts again", self.hello.serial,
                     applied.version, before.version)
        elif before is None and self.applied is not None and not self.applied.same_as(applied) \
                and self._being_pushed(msg):
            # the set this daemon is pushing, applied before its ack was heard (a cable out mid-push:
            # the read-back at the reconnect came first). Said "not written by this daemon" with a
            # WARNING (an integrator's fault campaign, F3); the push itself records the result
            self._watch_afresh()
            log.info("unit %s: it holds v%d, the set being pushed, before its ack was heard: the drift "
                     "monitor starts again on it", self.hello.serial, applied.version)
        elif before is None and self.applied is not None and not self.applied.same_as(applied):
            # unasked, the unit reports a set other than the one learning rebuilds its raw rate with:
            # a ground station wrote an autopilot's compensation (an integrator's audit: the daemon
            # learnt a curve doubled by the set it assumed and pushed one worse than none)
            self._watch_afresh()
            now_holds = f"{'another ' if applied.version == self.applied.version else ''}v{applied.version}"
            log.warning("unit %s: it now holds %s where v%d was, not written by this daemon: learning "
                        "and the drift monitor go on with the set it holds", self.hello.serial, now_holds,
                        self.applied.version)
            if self.state is State.MONITORING:  # it said "monitoring v2" while the unit held v0
                self.reason = (f"monitoring v{applied.version}, which replaced v{self.applied.version} "
                               "outside gyrocal")
            if self._retry is not None:
                # a set learnt before the change and refused then: pushed again, v1 (10 minutes old)
                # overwrote the calibration an ArduPilot had just learnt, 8-20x worse for a minute (an
                # integrator's re-check). A new set must now pass validation against the one held
                log.info("unit %s: v%d is not pushed again: the unit's set changed since", self.hello.serial,
                         self._retry["version"])
                self._retry = None
        if self.applied is None and self.caps.reboot_required and applied.version > 0 \
                and self.reboot_needed is None:
            # a PX4 that booted with TC_G_ENABLE 0 holds a set it applies only after its next reboot,
            # whoever wrote it (the link's write-back after a push cut by a reboot): status said
            # "applied v1, as the store says" with no reboot_needed while the boot applied nothing
            # (an integrator's audit)
            self.reboot_needed = {"version": applied.version, "why": f"the unit ({self.caps.kind}) started "
                                  "this boot with its compensation off: the set it holds applies only after "
                                  "its next reboot"}
            log.warning("unit %s: it holds v%d, which takes effect at its next reboot", self.hello.serial,
                        applied.version)
        if self.applied is None:
            # said once a session; a read again after a reconnect or a failed push is DEBUG (a set that
            # changed says so above): a flapping cable logged it at every flap (an operator's audit)
            log.log(logging.INFO if before is None else logging.DEBUG,
                    "unit %s holds calibration v%d (terms id 0x%04x)", self.hello.serial, applied.version,
                    applied.terms_id)
            self.reason = self._refused_terms() or "collecting still samples"
            self._end_blind()  # a failed push's samples up to here: their set is not known
        first = self.applied is None and before is None
        self.applied = applied
        self._read_asks = 0
        self._reconcile(msg)
        if first:
            self._adopt_unit_set(msg)
        if self._retry is not None and self.agreement.get("agree") and msg.version == self._retry["version"]:
            log.info("unit %s already holds v%d: no retry needed", self.hello.serial, msg.version)
            self._retry = None

    def _held_prior(self, version: int, coeffs: np.ndarray, stored: bool) -> tuple[Any, bool]:
        """The set the unit holds as a prior for a new learner: the store's applied record of it (when
        ``stored`` says to look and the store has one), else a record of the unit's coefficients [deg/s]
        whose quality off the poses seen is not known (no sphere figure). And whether it is the store's."""
        if stored:
            try:
                rec = self.store.get(self.hello.serial, version)
            except Exception:  # the store is unavailable: the unit's coefficients, as for an unknown set
                rec = None
            if rec is not None and rec.push.get("status") in APPLIED_STATUSES:
                return rec, True
        inf = {a: float("inf") for a in "xyz"}
        return CalibrationRecord(serial=self.hello.serial, version=version, terms=list(self.names),
                                 coefficients_dps=np.asarray(coeffs, dtype=float).tolist(),
                                 uncertainty_dps=[[None] * len(self.names)] * 3,
                                 stats={"predicted_drift_dph": {"left_sphere": inf}},
                                 push={"status": "unit"}), False

    def _adopt_unit_set(self, msg: CoeffReport) -> None:
        """The set the unit holds is the warm start's prior when it is not the one the session started
        from (the store's last held set, or none), before anything is learnt or pushed.

        - A set of the configured terms that the store has no acked record of (a new navigation
          computer, a wiped state directory, a set another host wrote, another set under a stored
          version's number): its bias is re-estimated from the first still second, its other terms
          kept. Cold, such a unit waited 168 s for a full tumble, and at one pose kept the old
          switch-on's bias for good (an operator's audit); warm-started from the store's older set, a
          unit back from a factory recalibration had its gravity terms overwritten, 18-19 deg/h off
          the pose where the unit's own set left 0.04-0.58 (an integrator's check). The quality of such
          a set is not known: the figures over the sphere are null, as for a constant alone.
        - A set the store holds as applied but is not the one the session started from: that record.
        """
        lr = self.learner
        if self.validated_rms is not None or self.last_push or lr.samples \
                or self.caps.own_boot_bias or self.caps.reboot_required:
            return
        ag = self.agreement
        known = bool(ag.get("agree")) and ag.get("store_status") in APPLIED_STATUSES
        if known and msg.version == self.warm_started_from:
            return
        if names_for(msg.terms_id) != tuple(self.names) or not self.applied.beyond_constant():
            return  # a constant alone says nothing of the other terms: the cold rules decide (constant alone)
        coeffs = np.asarray(msg.coeffs_dps, dtype=np.float64)
        if coeffs.shape != (3, len(self.names)) or not np.all(np.isfinite(coeffs)):
            return
        was = "none" if self.warm_started_from is None else f"v{self.warm_started_from}"
        prior, stored = self._held_prior(msg.version, coeffs, known)
        why = (f"the store's v{msg.version}, which the unit holds (the session started from {was})" if stored
               else f"the unit's own v{msg.version}, which the store has no acked record of (the session "
                    f"started from {was})")
        learner = Learner(self.cfg, prior, self.rate_hz)
        if learner.prior is None:
            return
        self.learner = learner
        self.warm_started_from = msg.version
        log.info("unit %s: warm start from %s: its bias re-estimated from the first still second",
                 self.hello.serial, why)

    # -- samples ------------------------------------------------------------------------------
    def feed(self, samples: np.ndarray, still: np.ndarray, now: float) -> None:
        """Learn from decided samples (SAMPLE_DTYPE) with their still flags."""
        self.samples += samples.size
        if samples.size == 0:
            return
        # dtemp follows the unit's rule from the session's first sample, also while the unit's set is
        # still being read: a copy started later is not the unit's for WINDOW seconds (TempRate.exact)
        dtemp, exact = self._trate.update_exact(samples["t"], samples["temp"], samples["seq"])
        self._t_last = float(samples["t"][-1])  # the newest decided sample's time [s]
        self.heard(self._t_last)
        if self._same_boot is not None:
            self._check_same_boot(float(samples["t"][0]))
        if self.samples == samples.size and int(samples["seq"][0]) == 0 \
                and float(samples["t"][0]) > FIRST_SAMPLE_MAX_S:
            log.warning("unit %s: its first sample (seq 0) is stamped %.1f s, but unit time counts "
                        "from switch-on (protocol.md, section 2): terms in t_on (a warm-up) will not "
                        "fit this unit", self.hello.serial, float(samples["t"][0]))
        if self.applied is None:
            return
        # t_on is the unit's time since switch-on, as the unit evaluates its set (protocol.md,
        # section 6), never the time since this daemon's first sample: a daemon that starts after
        # the unit (boot order, a restart) would otherwise learn a warm-up exp(-t_on/TAU) scaled by
        # exp(-delay/TAU) and push it (tests/test_t_on_unit_time.py)
        cols = {
            "t": samples["t"], "ax": samples["ax"], "ay": samples["ay"], "az": samples["az"],
            "temp": samples["temp"], "t_on": samples["t"], "dtemp": dtemp,
        }
        if not exact.all() and (self.applied.uses("dtemp") or (self._switch is not None
                                                                and self._switch[0].uses("dtemp"))):
            # the unit's compensation cannot be rebuilt exactly for these samples: neither learnt from
            # nor held out (a daemon that started 2.3 s after an independent fibre unit with a
            # 0.02 deg/s per degC/s factory term, in a 0.5 degC/s warm-up, pushed nothing in 150 s
            # on 5 of 8 seeds and cut 2.8-8x on the rest: tests/test_dtemp_exact.py)
            still = still & exact
            self.inexact_samples += int((~exact).sum())
            if not self._inexact_said:  # one line per stretch: a late start, a link gap
                self._inexact_said = True
                log.info("unit %s: still samples from unit time %.1f s set aside for up to %d s: this "
                         "host did not hear the unit from switch-on or lost a part of its stream, so "
                         "it cannot rebuild the unit's dT/dt yet", self.hello.serial,
                         float(samples["t"][int(np.argmin(exact))]), TempRate.WINDOW + 1)
        elif exact.all():
            self._inexact_said = False
        out = np.column_stack([samples["wx"], samples["wy"], samples["wz"]])
        c_ref = None
        if self.earth is not None:  # true rate at rest, not drift (earth_track.py)
            acc_g = np.column_stack([samples["ax"], samples["ay"], samples["az"]])
            c_ref = self.earth.advance(samples["seq"], samples["t"], out, acc_g, still)
            clean = self.earth.known & np.isfinite(c_ref[:, 0, 0])
            north_part = self.earth.horizontal_dps(c_ref)  # the fit's sums take the rate with it in
            out = out - vertical_earth_rate_dps(acc_g, self.earth.latitude_deg) - north_part
        rate = np.abs(cols["dtemp"])
        rate = rate[np.isfinite(rate)]
        if rate.size:  # the fastest warming this session, for refine.settled
            self._peak_trate = max(self._peak_trate, float(rate.max()))
        # learn on gravity as a unit vector (gx^2 + gy^2 + gz^2 = 1 exactly, so the structural null
        # direction is exact); the unit applies its set on the measured accel, hence raw below
        phi = block_terms(self.spec, cols)
        raw = out + self._compensation(samples["seq"], cols, phi)
        if c_ref is not None and still.any():
            # every still sample finds north (earth_track.py); once it was found, a sample whose
            # reference has no north yet (lost, found again from a rest or two) teaches nothing else
            self.earth.add(phi[still], raw[still] + north_part[still], c_ref[still])
        if c_ref is not None and self.earth.found_before:
            still = still & clean
        still = self._outside_blind(samples["t"], still)
        blocks, train = self.acc.feed(raw, out, phi, still)
        for b in blocks:  # when, on the unit's clock: a wandering bias is validated on recent blocks
            b.t_s = self._t_last
        self.still_samples += int(still.sum())
        if self._has_temp and still.any():
            t = samples["temp"][still]
            ok = np.isfinite(t)
            t = t[ok]
            if t.size and self.learner.cold_bias:
                self._track_steady(samples["t"][still][ok], t)
            if t.size:
                lo, hi = float(t.min()), float(t.max())
                self.temp_seen = (lo, hi) if self.temp_seen is None else \
                    (min(lo, self.temp_seen[0]), max(hi, self.temp_seen[1]))
        if train.any() and self.state is not State.PUSHING:
            self.learner.update_many(phi[train], raw[train], samples["t"][train])
        self.holdout.add([b for b in blocks if b.holdout])
        self.monitor.add(blocks)
        self.learnt.add(blocks)
        self._learnt_n += len(blocks)
        self._note_poses(blocks, cols)

    def _track_steady(self, t_s: np.ndarray, temp_c: np.ndarray) -> None:
        """How long [s] the temperature [degC] has stayed within STEADY_BAND_C of where its band began
        (a sample outside starts a new band there)."""
        ref = self._steady_from or (float(t_s[0]), float(temp_c[0]))
        out = np.flatnonzero(np.abs(temp_c - ref[1]) > self.STEADY_BAND_C)
        if out.size:
            ref = (float(t_s[out[-1]]), float(temp_c[out[-1]]))
        self._steady_from = ref
        self._steady_s = float(t_s[-1]) - ref[0]

    def _outside_blind(self, t_s: np.ndarray, still: np.ndarray) -> np.ndarray:
        """``still`` without the samples [unit time, s] whose set is not known (``_blind``).

        Why: the unit may apply a write whose ack is lost (a bus silence, noise), and the retry's ack
        comes seconds later; the samples between were rebuilt with the set held before. 3 s after the
        push, the drift monitor read 21-29 deg/h where the unit left 0.5-1.3 and raised an alarm (an
        integrator's CAN campaign, 2 runs of 2). An autopilot applies its parameters one by one while
        they are written. Such samples are neither learnt, nor held out, nor monitored."""
        b = self._blind
        if b is None or not t_s.size:
            return still
        lo, hi = b
        blind = t_s > lo if hi is None else (t_s > lo) & (t_s <= hi)
        if hi is not None and t_s[-1] > hi:
            self._blind = None  # every sample of the window has been decided
        if not blind.any():
            return still
        self.blind_samples += int(blind.sum())
        return still & ~blind  # not still: the block being filled ends before the window (blocks.py)

    def _cold_bias_check(self) -> str:
        """Let a cold start whose data has stopped adding directions learn its constant alone
        (STEADY_S); what it waits for, or ""."""
        lr = self.learner
        if not lr.cold_bias or lr.cold_ready or self._bias_pushed or self.validated_rms is not None \
                or lr.samples == 0:
            return ""
        if self.applied is None:
            return ""
        if self.applied.beyond_constant():
            # a curve the unit holds (a factory calibration, another tool's thermal one) is not replaced
            # by a constant; a constant it holds (PX4's CAL_GYRO offsets) is, when the new one removes
            # enough drift (the gate). Said: a unit holding another term list at one pose waited with
            # only "rank 1 < 9" to show for it (an integrator's check)
            held = "" if self.applied.terms_id == terms_id(self.names) else \
                f" of other terms (0x{self.applied.terms_id:04X})"
            return (f"; the unit holds v{self.applied.version}, a set{held} beyond a constant, which a "
                    "constant alone would replace: the first set here is a full one")
        rank = lr.rank
        if rank >= lr.full_rank or lr.held_zero is not None:
            # the data has reached the rank (or that of the terms not held at 0): a full set is what is
            # held back (by the store, the gate); "learning its constant alone ... until the data
            # reaches the rank" was said at rank 9 of 9, before a full set was pushed (an operator's audit)
            return ""
        stalled = self._rank_stalled()
        waits = [] if stalled >= self.STEADY_S else [f"no new direction learnt for {stalled:.0f} s"]
        if self._has_temp and self._steady_s < self.STEADY_S:
            waits.append(f"the temperature within {self.STEADY_BAND_C:g} degC for {self._steady_s:.0f} s")
        if waits:
            return (f"; a constant alone is learnt first once, for {self.STEADY_S:.0f} s, the data adds no "
                    f"direction{' and the temperature stays put' if self._has_temp else ''} "
                    f"({', '.join(waits)} so far)")
        lr.cold_ready = True
        lo, hi = self.temp_seen or (float("nan"), float("nan"))
        seen = f", {lo:.1f}..{hi:.1f} degC" if self._has_temp else ""
        log.info("unit %s: no new direction learnt for %.0f s (rank %d of %d, %d poses%s) and the unit "
                 "holds no set: learning its constant alone, every other term 0, until the data reaches "
                 "the rank", self.hello.serial, stalled, rank, lr.full_rank, len(self.poses), seen)
        return ""

    def _rank_stalled(self) -> float:
        """How long [s of unit time] no new direction has come this switch-on: since the learner's
        rank last rose above the highest it has reached. A learner started again from nothing after
        a bias step (``_step_found``) regains the directions already seen; counted as new, they made
        a cold unit on a road drive wait its 60 s for its constant alone again (the set at 122 s,
        78 s without the step; an outside re-check and in process)."""
        rank = self.learner.rank
        if rank > self._rank_since[0]:
            self._rank_since = (rank, self._t_last)
        return self._t_last - self._rank_since[1]

    def _hold_check(self) -> None:
        """Let a cold start whose rank stalled short of the structural rank hold at 0 the terms its
        data cannot separate (HOLD_STALL_S), and say which, once each time they change."""
        lr = self.learner
        if lr.prior is not None or lr.samples == 0:
            return
        stalled = self._rank_stalled()
        if not lr.may_hold:
            if lr.rank >= lr.full_rank or stalled < self.HOLD_STALL_S:
                return
            lr.allow_hold()
        held = lr.held_zero
        if held is None:  # the rank grew: to the full one, or to one no choice of terms fits yet
            if self._held_said and lr.rank >= lr.full_rank:
                log.info("unit %s: rank %d of %d: every term is learnt now", self.hello.serial, lr.rank,
                         lr.full_rank)
                self._held_said = []
            return
        names = held.names(self.names)
        if names == self._held_said:
            return
        ident = lr.identifiable()
        log.info("unit %s: rank %d of %d, no new direction for %.0f s: the data cannot separate %s "
                 "(on the data: %s); learning the set with %s held at 0 until a later warm-up "
                 "separates them", self.hello.serial, lr.rank, lr.full_rank, stalled,
                 ", ".join(ident["undetermined_terms"]), "; ".join(f"{u} = 0" for u in ident["undetermined"]),
                 ", ".join(names))
        self._held_said = names

    def heard(self, t_unit: float) -> None:
        """The unit's clock [s] as of the newest sample heard. The engine calls it before the still
        detector, which holds samples back for a second or more at a session's start: an operator's
        rollback in that second is recorded with the unit time of its push too."""
        if not self.unit_clock_s >= t_unit:  # NaN at first
            self.unit_clock_s = t_unit

    def _check_same_boot(self, t_unit: float) -> None:
        """Whether this session resumes the switch-on of the set the unit holds, from its first sample.

        The boot counter alone is the unit's word (protocol.md: +1 per switch-on, kept in flash); the
        unit's clock counts from switch-on, so it must also have gone on from the push's time [s].

        A resumed session whose held set is a full set pushes no bias stage: that set was learnt over
        this switch-on's poses, and a bias-only set from one still pose replaced it with no gain (an
        operator's audit; ``benchmarks/bench_resume.py --no-resume``, 4 restarts 30 s apart, demo seeds
        1-6: two bias stages each on seeds 3 and 4, leaving 0.32/0.36/0.18 and 0.29/0.32/0.36 deg/h;
        resumed, none, leaving 0.34/0.27/0.19 and 0.28/0.28/0.35). Over a held bias stage, itself from
        one second, the bias stage stays: skipping it there left 0.27/0.71/0.68 deg/h on seed 5, where
        redoing it leaves 0.32/0.32/0.34. It learns on for a full set either way."""
        sb, self._same_boot = self._same_boot, None
        if sb is None:
            return
        if t_unit >= sb["time_s"]:
            self.resumed_from = int(sb["version"])
            self._bias_pushed = sb["stage"] != "bias"
            if self.caps.reboot_required:  # acked in this boot by a unit that applies sets at its reboot
                self.reboot_needed = {"version": self.resumed_from, "why": f"the unit ({self.caps.kind}) "
                                      "applies a pushed set only after its next reboot"}
            v = sb["version"]
            kind = "a full set" if sb["stage"] == "full" else "an operator's set"
            then = (f"v{v} is {kind}: no bias stage, learning on for a full set"
                    if self._bias_pushed else f"v{v} is a bias-only set: its bias stage may be redone")
            log.info("unit %s: the same switch-on as v%d (boot %d; unit time %.1f s, %.1f s at its push): "
                     "this daemon restarted; %s", self.hello.serial, v, self.hello.boot_count, t_unit,
                     sb["time_s"], then)
            # the switch-on's push is this session's too: status said "last push: none yet" after a
            # restart, and an operator's set lost its hold, so the next validation pushed over it
            if not self.last_push:
                self.last_push = {**sb["push"], "version": v, "resumed": True}
            if sb.get("operator"):
                self._bias_pushed = True
                self.hold_for_operator(v, f"{sb['operator']}, before this daemon restarted")
        else:
            log.warning("unit %s: boot %d again, but the unit's clock went back (%.1f s, %.1f s at v%d's "
                        "push): a new switch-on whose boot counter did not count; calibrating it as one",
                        self.hello.serial, self.hello.boot_count, t_unit, sb["time_s"], sb["version"])

    def _note_poses(self, blocks: list[Any], cols: dict[str, np.ndarray]) -> None:
        """Remember the distinct poses seen (block-mean terms), for the predicted drift (poses.py)."""
        self._context = {k: float(np.mean(v)) for k, v in cols.items() if k not in ("ax", "ay", "az")}
        for b in blocks:
            self.pose_log.note(b.phi)

    @property
    def poses(self) -> list[np.ndarray]:
        """Block-mean terms (P,) of the distinct poses seen."""
        return self.pose_log.poses

    def _sphere_phi(self, at: dict[str, float] | None = None) -> np.ndarray:
        """Terms (M, P) over the sphere of gravity directions, the other inputs at their latest values
        (``at`` overrides some of them, e.g. the temperature [degC])."""
        n = SPHERE_G.shape[0]
        cols = {k: np.full(n, v) for k, v in {**self._context, **(at or {})}.items()}
        cols.update({"ax": SPHERE_G[:, 0], "ay": SPHERE_G[:, 1], "az": SPHERE_G[:, 2]})
        cols.setdefault("t", np.zeros(n))
        return block_terms(self.spec, cols)

    def predict(self) -> dict[str, Any]:
        """The learner's predicted drift [deg/s] left by the current set (see learner.py)."""
        applied = self._applied_coeffs()
        poses = self.pose_log.array(len(self.names))
        p = self.learner.prediction(poses, self._sphere_phi(), applied, self.holdout.blocks)
        # the unit is judged at poses the daemon may not have seen yet: an upper bound on what a set
        # leaves is the worse of the poses seen and the sphere (inf while the sphere is undetermined)
        p["bound"] = np.fmax(p["left_poses"], p["left_sphere"])
        # the unit's rests are at poses seen and at poses not seen yet, in a share estimated by
        # Good-Turing from how often it comes back to poses already seen. The gate's figure (``left``)
        # takes the bound for the poses not seen yet; the figure to expect takes the geometric mean of
        # the two: the sphere's mean square is dominated by the few directions the data determines
        # worst, which a handful of unseen poses seldom hit (in process, against an independent
        # unit's own poses: within 2x on 760 of 819 first-push axes, bench_indep.py --inprocess)
        u = self.pose_log.unseen_share()
        p["unseen_share"] = u
        with np.errstate(invalid="ignore"):
            seen2 = (1.0 - u) * p["left_poses"] ** 2
            p["left"] = np.sqrt(seen2 + u * p["bound"] ** 2)
            p["expected"] = np.sqrt(seen2 + u * p["left_poses"] * p["left_sphere"])
        self.prediction = p
        return p

    def _gate(self) -> tuple[bool, str]:
        """The push gate on the predicted drift left (deg/h in the reason)."""
        p = self.predict()
        # the bias stage is judged on what it learns (the bias); the stored terms' error is reported
        left, removes = p.get("gate", p["left"]), p["removes"]
        target = self.cfg.push["target_drift_dph"] / DPH
        bias = p.get("stage") == "bias"
        cut = self.BIAS_MIN_CUT if bias else self.cfg.push["min_cut"]
        # a refinement of a set this daemon pushed is judged per axis (refine.py); the bias stage and
        # a unit set the daemon knows nothing of: every axis must gain
        held_left, held_range, held_kept = (None, None, None) if bias else self._held_info()
        settled = refine.settled(self._trate.value, self._peak_trate)
        edge = settled and self._edge_costs(held_range, cut)
        # widened past the held set's range, and past the range this session's last full set was pushed
        # over: a refinement that keeps the held rows on an axis records the held set's range, and a
        # warm-up pushed every 10 s, each push widened past that range again (a 0x549E unit)
        pushed = self._range_pushed
        ref = held_range if held_range is None or pushed is None else \
            (min(held_range[0], pushed[0]), max(held_range[1], pushed[1]))
        wide = refine.widened(ref, self.temp_seen, settled, edge)
        if wide and held_left is not None:
            # beyond its own range the held set leaves what it leaves there, not its recorded figure
            # (4.5 deg/h credited where an ArduPilot clamping above TMAX was left 600 deg/h off, and a
            # refinement leaving 50 held back for good: an integrator's re-check)
            edge_left = self._edge_left(held_range)
            if edge_left is not None:
                held_left = np.fmax(held_left, edge_left)
        # a set pushed before north was found holds the Earth's rate along north as drift: like a
        # widened temperature range, the next set need not cut 1/min_cut of what it changes, only be
        # no worse on any axis (and pass validation)
        wide = wide or self._held_has_north
        floor = None if bias else self.learner.wander_floor(self.cfg.push["wander_horizon_s"])
        holds = not bias and self.applied is not None and self.applied.version > 0
        g = self._gate_result = refine.gate(left, removes, target, cut, held_left, wide, floor,
                                            self.cfg.validation["min_improvement"], held_kept, holds)
        self._keep_held = None
        if bias and not g.ok and self._applied_coeffs() is not None and np.all(np.isfinite(left)) \
                and np.any(g.gains):
            # the axes that gain get the new bias now; the others keep the held one until theirs gains
            # too (another bias-stage push). All axes had to gain at once: an axis whose bias repeats
            # from one switch-on to the next held the other two 1130 and 2874 deg/h off for good (a
            # serial integrator's unit)
            self._keep_held = ~g.gains
            return True, (f"bias stage on axis {_axes(g.gains)}; axis {_axes(~g.gains)} keeps the held bias "
                          f"for now (moved {_dph(removes)} deg/h, the new bias's error {_dph(left)} deg/h: "
                          f"pushed once it moves {cut:g}x its error)")
        share = min(cut, refine.HELD_CUT) if holds else cut
        n = len(self.poses)
        why = (f"predicted drift left {_dph(left)} deg/h over {n} pose{'' if n == 1 else 's'}, "
               f"{p['unseen_share']:.0%} of the coming rests expected at poses not seen yet; it must be "
               f"below {self.cfg.push['target_drift_dph']:g} deg/h or 1/{share:g} of the {_dph(removes)} "
               "deg/h the set removes")
        if floor is not None:
            why += (f" (or {refine.WANDER_LEFT_SHARE:g} of the bias wander's {_dph(floor)} deg/h over "
                    f"{self.cfg.push['wander_horizon_s']:g} s, the push cutting the total by "
                    f"{self.cfg.validation['min_improvement']:.0%})")
        if held_left is not None:
            why += " on some axis"
            if self.temp_seen is not None or held_range is not None:  # a model with temperature terms
                why += (f" (or the range seen {_range(self.temp_seen)} degC widen the held set's "
                        f"{_range(held_range)} degC)")
            why += f", leaving no axis worse than the held set's {_dph(held_left)} deg/h"
            version = self.applied.version if self.applied is not None else -1
            if wide and not g.ok and version not in self._refusal_logged:
                self._refusal_logged.add(version)  # once per held set: the gate runs 4 times a second
                log.info("unit %s: the range has widened past v%d's, but the refinement is held back: %s",
                         self.hello.serial, version, why)
        return g.ok, why

    def _edge_costs(self, held_range: tuple[float, float] | None, cut: float) -> bool:
        """Whether the held set leaves, at an end of the range seen beyond its own, more than 1/``cut``
        of the unit's drift on some axis (refine.edge_costs). The unit's drift is the learnt set's RMS
        over the poses seen, uncompensated."""
        worst = self._edge_left(held_range)
        c = self.learner.coefficients
        poses = self.pose_log.array(len(self.names))
        if worst is None or not len(poses):
            return False
        drift = np.sqrt(np.mean((poses @ c.T) ** 2, axis=0))
        return refine.edge_costs(worst, drift, cut)

    def _edge_left(self, held_range: tuple[float, float] | None) -> np.ndarray | None:
        """The drift [deg/s] (3,) the held set leaves at the worse end of the range seen beyond its own,
        or None (no such end, or nothing to judge it by): the learnt set minus the held one at that
        temperature (RMS over the sphere of gravity directions, the other inputs at their latest
        values); a unit that clamps its temperature into TMIN..TMAX (capabilities) evaluates the held
        set at the nearer limit."""
        temps = refine.edge_temps(held_range, self.temp_seen)
        a = self._applied_coeffs()
        if not temps or held_range is None or a is None or "temp" not in self._context:
            return None
        c = self.learner.coefficients
        if not np.all(np.isfinite(c)):
            return None
        worst = np.zeros(3)
        for t in temps:
            held_t = min(max(t, held_range[0]), held_range[1]) if self.caps.clamps_temperature else t
            at_t = self._sphere_phi({"temp": t}) @ c.T
            held = self._sphere_phi({"temp": held_t}) @ a.T
            worst = np.fmax(worst, np.sqrt(np.mean((at_t - held) ** 2, axis=0)))
        return worst

    def _held_info(self) -> HeldInfo:
        """The held set's predicted drift left [deg/s] (3,), temperature range [degC] and kept axes
        ((3,) bool: where it kept an older set's bias, its ``kept_axes``) as its store record has
        them; all None for a set this daemon has no acked record of."""
        a = self.applied
        if a is None or a.version <= 0:
            return None, None, None
        if a.version in self._held_cache:
            return self._held_cache[a.version]
        try:
            rec = self.store.get(self.hello.serial, a.version)
        except Exception:  # the store is unavailable: unknown for now, asked again at the next gate
            return None, None, None
        if rec is None:  # a set this daemon never recorded (factory, another tool): stays unknown
            self._held_cache[a.version] = (None, None, None)
            return None, None, None
        if rec.push.get("status") not in APPLIED_STATUSES:  # a set acked, or applied with its ack lost
            return None, None, None  # not cached: an ack the store could not record yet may come later
        left: np.ndarray | None = None
        rng: tuple[float, float] | None = None
        pred = (rec.stats or {}).get("predicted_drift_dph") or {}
        left_dph = pred.get("left") or {}
        if all(isinstance(left_dph.get(k), int | float) for k in "xyz"):
            left = np.array([left_dph[k] for k in "xyz"], dtype=float) / DPH
        r = (rec.stats or {}).get("temp_range_c")
        if isinstance(r, list) and len(r) == 2 and all(isinstance(v, int | float) for v in r):
            rng = (float(r[0]), float(r[1]))
        kept_axes = pred.get("kept_axes")
        kept = np.array([ax in kept_axes for ax in "xyz"]) if kept_axes else None
        self._held_cache[a.version] = (left, rng, kept)
        return left, rng, kept

    def _compensation(self, seq: np.ndarray, cols: dict[str, np.ndarray],
                      phi: np.ndarray | None = None) -> np.ndarray:
        """What the unit subtracted from each sample, (N, 3) [deg/s], switching sets at the ack.

        ``phi``: the session's terms of these cols, reused when the unit's set has the same terms."""
        a = self.applied
        same = phi is not None and a is not None and tuple(a.names) == tuple(self.names)
        comp = a.compensation(cols, phi if same else None) if a is not None else np.zeros((seq.size, 3))
        if self._switch is None:
            return comp
        new, last_seq = self._switch
        if last_seq is None:
            after = np.ones(seq.size, dtype=bool)
        else:
            d = (seq.astype(np.int64) - last_seq) % SEQ_MODULO  # seq after last_seq, across the u32 wrap
            after = (d > 0) & (d < (1 << 31))
        if after.any():
            comp[after] = new.compensation({k: v[after] for k, v in cols.items()})
            self.applied, self._switch = new, None
            self.acc.discard_partial()  # a block must not mix outputs of two sets
        return comp

    # -- time ---------------------------------------------------------------------------------
    def tick(self, now: float) -> None:
        if self.unrecorded and now >= self._store_retry_at:
            self._flush_unrecorded(now)
        if self._reconcile_again and now >= self._store_retry_at:
            self._settle_again(now)
        if self.push is not None:
            self.push.tick(now)
            if self.push.finished:
                self._after_push(now)
            return
        if self._push_due is not None:
            if self.unit_clock_s >= self._push_due["heard"]:
                due, self._push_due = self._push_due, None
                self.start_push(due["version"], due["names"], due["coeffs"], now)
            return
        if self.applied is None:
            if now >= self._read_deadline:
                # a link that takes no sends is the link's fault, said once by _send: not the unit's
                if self._read_asks == self.READ_WARN_AFTER and not self._link_warned:
                    # a report refused (NaN, bad CRC) is an answer, not silence (an integrator's audit)
                    what = (f"answered {self._read_asks} COEFF_READs only with reports that cannot be used "
                            f"({self.refused_reports} refused)" if self.refused_reports
                            else f"not answered {self._read_asks} COEFF_READs")
                    log.warning("unit %s has %s: counting samples but not learning (learning needs the set "
                                "the unit applies); asking again, less often", self.hello.serial, what)
                if self._link_warned:
                    self.reason = "the link takes no sends: the unit's set is read again when it returns"
                elif self._read_asks >= self.READ_WARN_AFTER and not self.refused_reports:
                    self.reason = (f"no usable COEFF_REPORT from the unit ({self._read_asks} COEFF_READs): "
                                   "counting samples, not learning; is it a listen-only replay, a unit "
                                   "without COEFF_READ support, or are its reports dropped by the link "
                                   "(link.errors: crc, bad_values)?")
                self.request_read(now)
            return
        if self._retry is not None and now >= self._retry["at"]:
            r, self._retry = self._retry, None
            log.info("unit %s: pushing v%d again (round %d%s)", self.hello.serial, r["version"], r["round"],
                     ", its failures said at INFO" if r["round"] >= 2 else "")
            self.start_push(r["version"], r["names"], r["coeffs"], now, retry_round=r["round"])
            return
        if now < self._next_check:
            return
        self._next_check = now + self.CHECK_EVERY_S
        if self.earth is not None:
            again = self.earth.found_before
            if self.earth.fit(self.learner.full_rank):
                if again:  # the drift was learnt clean: nothing to learn again
                    log.log(logging.INFO if self.earth.references == 2 else logging.DEBUG,
                            "unit %s: north found again after the reference was lost (%d references so "
                            "far; heading 1-sigma %.1f deg)", self.hello.serial, self.earth.references,
                            self.earth.heading_sigma_deg)
                else:
                    self._north_found()
        if self.state in (State.COLLECTING, State.CONVERGED, State.MONITORING):
            if self._unwatched() and self._step_found():
                return  # no alarm can start learning again: it starts again after the step
            self._watch_held()
            if self.validated_rms is not None or self._watch_rms is not None:
                # a set of this session is held: its drift is watched whatever learning is doing. In
                # COLLECTING (a bias stage refused after an alarm) a second step of the bias went
                # unwatched, and the sets that followed averaged it in: x 30, 15, then 7.5 deg/h off
                # with the alarm off (an outside re-check: 54-68 deg/h on a road drive)
                self._check_alarm()
            self._check_convergence(now)

    def hold_for_operator(self, version: int, what: str) -> None:
        """An operator's rollback or file push stands for the rest of this session: the daemon keeps
        learning but pushes no set of its own over it (it pushed a full set over a rollback 24 s later,
        with no word why: an operator's audit). A new switch-on or `gyrocal recalibrate` ends it; a
        daemon restarted within the switch-on keeps it (the acked record says ``push.operator``)."""
        self._operator_push = (version, what.split(",")[0])
        self.operator_hold = (f"holding the operator's v{version} ({what}): no set of the daemon's own is "
                              "pushed until the next switch-on or `gyrocal recalibrate`; learning goes on")
        log.info("unit %s: %s", self.hello.serial, self.operator_hold)

    def _north_found(self) -> None:
        """North is fixed (earth_track.py): from here on the Earth's whole rotation is taken out of
        every sample, and learning starts again, because what was learnt so far held the part along
        north (a set already pushed stays; the next validation refines it)."""
        e = self.earth
        log.info("unit %s: north found from the tumble (heading 1-sigma %.1f deg, Earth rate fit %.2f x "
                 "its latitude's): the Earth's rotation is taken out of the samples from now on, and "
                 "learning starts again", self.hello.serial, e.heading_sigma_deg, e.fit_magnitude)
        if not 0.7 <= e.fit_magnitude <= 1.3:
            log.warning("unit %s: the horizontal Earth rate fitted is %.2f x that of site.latitude_deg "
                        "%.4g: check the latitude", self.hello.serial, e.fit_magnitude, e.latitude_deg)
        self._held_has_north = self.validated_rms is not None  # a set of this session is held
        self._learn_again(self.learner.fresh())

    def _learn_again(self, learner: Learner) -> None:
        """Learning starts again with ``learner``: new blocks, an empty monitor, the next validation due
        once the new data supports one (north found; a drift alarm)."""
        self.learner = learner
        self._new_blocks()
        self.monitor.clear()
        self._next_validation_at = 0
        self._validated_at = 0
        self._rank_validated = 0
        self._said_converged = False
        if self.state in (State.CONVERGED, State.VALIDATING):
            self.state = State.COLLECTING

    def _new_blocks(self) -> None:
        """Empty still-block accumulator and held-out window (at start, and when learning starts again)."""
        block = int(round(self.cfg.validation["block_s"] * self.rate_hz))
        self.acc = BlockAccumulator(block, self.cfg.validation["holdout_every"], len(self.names))
        self.holdout = BlockWindow(512)
        self.learnt = BlockWindow(self.STEP_WINDOW_BLOCKS)  # every still block learning has seen
        self._learnt_n = self._step_checked = 0  # blocks added to it, and that count at the last check

    def _refused_terms(self) -> str | None:
        """Why the unit will not take this session's term set (a NAK UNKNOWN_TERMS), or None."""
        return self._unknown_terms.get(terms_id(self.names)) if self._unknown_terms else None

    def _check_convergence(self, now: float) -> None:
        """COLLECTING -> CONVERGED -> VALIDATING; in MONITORING, re-validate as evidence grows."""
        monitoring = self.state is State.MONITORING
        self.next_set_waits = None
        if self.unconfirmed is not None:  # learn, but record and push nothing under a guessed serial
            self.reason = self.unconfirmed
            return
        if self.operator_hold is not None:  # an operator's set stands until the next session
            self.reason = self.operator_hold
            return
        if self.range_hold is not None:
            self.reason = self.range_hold
            return
        self._hold_check()
        waits = self._cold_bias_check()
        if self._bias_stage_due():
            self._push_bias(now)
            return
        ok, why = self.learner.converged
        if not ok:
            why += waits
        if ok:
            ok, gate_why = self._gate()
            if not ok:
                why = "converged, but " + gate_why
        # while monitoring, the reason stays "monitoring vN" and the next set's wait is said beside it:
        # an aged unit left 1.2-1.8 deg/h off showed no sign of why no refinement came (rc35 N3)
        self.next_set_waits = None if not monitoring or ok else \
            f"the bias stage: {why}" if self.learner.bias_only else why
        if not ok:
            self._said_converged = False
            if not monitoring:  # a set the unit refused stays the first thing the status says
                refused = self._refused_terms()
                self.state, self.reason = State.COLLECTING, why if refused is None else f"{refused}; {why}"
            return
        # after a push the next validation waits for twice the samples; a temperature range that has
        # widened past the held set's (refine.py) is worth a look sooner, at 10 % more samples; so is
        # data that has determined a direction more than the last validation's: a unit at one pose
        # given its constant alone at 62 s, then tumbled, reached rank 9 in 20 s and waited 145 s more
        # for twice the samples (an integrator's CAN campaign)
        early = (self._gate_result is not None and self._gate_result.widened
                 and self.learner.samples >= 1.1 * self._validated_at) \
            or self.learner.rank > self._rank_validated
        if self.learner.samples < self._next_validation_at and not early:
            if not monitoring and self.last_validation.get("passed") is False:
                self.reason = "validation failed before; collecting more samples"
            elif monitoring and self.last_validation.get("passed") is False and self._refused_why:
                # the gate passed, validation did not: said too, or the field was null most of the time
                # on a unit at rest (rc35 re-check)
                self.next_set_waits = (f"{self._refused_why}; validated again after "
                                       f"{self._next_validation_at - self.learner.samples} more samples")
            return  # else the reason a validated set was not pushed stays what the status says
        if self.state is State.COLLECTING and not self._said_converged:
            # once per stretch of convergence: a store that refuses the set sends the session back to
            # COLLECTING at every check, and this line came 4 times a second (an operator's audit)
            self._said_converged = True
            log.info("unit %s: estimator %s", self.hello.serial, why)
        need = self.cfg.validation["min_holdout_blocks"]
        if not monitoring:
            self.state = State.CONVERGED
        if len(self.holdout) < need:
            if not monitoring:
                self.reason = f"converged; waiting for held-out blocks ({len(self.holdout)}/{need})"
            return
        self._validate(now)

    def _bias_stage_due(self) -> bool:
        """A warm start's bias-only set is due: first still second seen, not pushed yet this session
        (or pushed on some axes only, ``_bias_partial``: the others when theirs gains)."""
        return (bool(self.cfg.push.get("bias_first", True)) and not self._bias_pushed
                and self.learner.bias_only
                and (self.validated_rms is None or self._bias_partial or self._relearning)
                and self.learner.samples >= self.BIAS_MIN_S * self.rate_hz and len(self.monitor) >= 2
                # a partial stage whose validation failed waits as a full set does (it was tried again at
                # every tick, 8 log lines a second: a serial integrator's re-check)
                and (not self._bias_partial or self.learner.samples >= self._next_validation_at))

    def _push_bias(self, now: float) -> None:
        """Stage 1 after a switch-on: the stored set with this switch-on's bias, validated on the blocks
        seen (the bias is a mean: there is nothing to over-fit), pushed as soon as the gate passes."""
        ok, why = self._gate()
        if not ok:
            self.reason = "bias stage: " + why
            return
        self._bias_partial = self._keep_held is not None
        self._bias_pushed = not self._bias_partial
        after_alarm, self._relearning = self._relearning, False
        if self._bias_partial and why != self._bias_said:
            self._bias_said = why
            log.info("unit %s: %s", self.hello.serial, why)
        self._validate(now, self.monitor, stage="bias")
        if after_alarm and self.push is not None:
            self._relearn_stages.add(self.push.write.version)

    def _bias_unsent(self, stage: str) -> None:
        """A bias stage the store could not record was not pushed: it is due again when the store
        returns. Marked done, a full set learnt over 8 poses came first instead and replaced the held
        18-pose gravity terms with ones 3-6x worse, for good (an integrator's CAN campaign, 2 of 2)."""
        if stage == "bias":
            self._bias_pushed = False
            self.learner.owe_bias = True

    def _validate(self, now: float, blocks: BlockWindow | None = None, stage: str = "full") -> None:
        self.state = State.VALIDATING
        if self._step_found(every_block=True):
            return  # a set learnt across the step would take its average, and its residual as the alarm's
        self._validated_at = self.learner.samples
        self._rank_validated = self.learner.rank
        # what the unit can hold (capabilities.py): validated, recorded and pushed; the rest is reported
        held = self.caps.held_subset(self.names)
        if held is None:
            self.state = State.COLLECTING
            self.reason = (f"validated set not pushed: the unit ({self.caps.kind}) holds none of the term "
                           f"sets {self.caps.as_dict()['term_sets']} within {self.names}")
            self._next_validation_at = int(self.learner.samples * 1.5) + 1
            log.warning("unit %s: %s", self.hello.serial, self.reason)
            return
        poses = self.pose_log.array(len(self.names))
        learnt = self.learner.coefficients
        blocks = self.holdout if blocks is None else blocks
        applied = self._applied_coeffs()
        keep = self._keep_held if stage == "bias" else None
        if keep is not None and applied is not None:
            learnt = np.where(keep[:, None], applied, learnt)  # the axes whose bias has not moved
        self._projection = proj = project(self.names, learnt, held, poses)
        coeffs = proj.embedded_dps
        # None: the unit's output as sent
        rms_old, rms_new = blocks.paired_rms(applied, coeffs, self.VALIDATION_TRIM)
        g = self._gate_result
        refining = stage == "full" and g is not None and self._held_info()[0] is not None
        worse = ~refine.axes_not_worse(rms_old, rms_new) if refining else np.zeros(3, dtype=bool)
        if refining and applied is not None and np.any(worse) and not np.all(worse):
            # the held set's rows on the axes where the new set is worse, the new rows elsewhere (each
            # axis's drift has its own coefficients): one worse axis refused gains of 50-250x on the
            # other two, for good (a serial integrator's unit whose y bias repeats)
            keep = worse
            learnt = np.where(keep[:, None], applied, learnt)
            self._projection = proj = project(self.names, learnt, held, poses)
            coeffs = proj.embedded_dps
            rms_old, rms_new = blocks.paired_rms(applied, coeffs, self.VALIDATION_TRIM)
            worse = ~refine.axes_not_worse(rms_old, rms_new)
        old2, new2 = float(np.sum(rms_old**2)), float(np.sum(rms_new**2))
        need = (1.0 - self.cfg.validation["min_improvement"]) ** 2
        self.last_validation = {
            "blocks": len(blocks), "stage": stage,
            "rms_current_dps": dict(zip("xyz", rms_old.tolist(), strict=True)),
            "rms_new_dps": dict(zip("xyz", rms_new.tolist(), strict=True)),
        }
        kept = [] if keep is None else [a for a, k in zip("xyz", keep, strict=True) if k]
        if kept:
            self.last_validation["kept_axes"] = kept
        # a refinement is not worse on any axis, and improves by min_improvement on the three axes
        # together or on one, or widens the range: a gain in TMIN..TMAX the held-out residual cannot
        # show (the link reconstructs the unit's output with the held set unclamped)
        enough = new2 <= need * old2
        # a first set on a unit whose bias wanders (a kf spec with a walk or a flicker floor): the
        # wander sits in every held-out block beside the noise and no set removes it, so the totals
        # cannot fall by min_improvement however good the set. It passes when its gain is significant,
        # paired per block (blocks.paired_gain_z), on the held-out blocks of the last
        # push.wander_horizon_s (the set holds the bias as it is now, older blocks had another; all
        # blocks while fewer than min_holdout_blocks are recent). The gate has already asked that the
        # predicted total, with the wander's floor, fall by min_improvement (refine.gate)
        if not enough and stage == "full" and not refining and self.validated_rms is None \
                and g is not None and g.floor is not None:
            recent = blocks.since(self._t_last - float(self.cfg.push["wander_horizon_s"]))
            judged = recent if len(recent) >= self.cfg.validation["min_holdout_blocks"] else blocks
            r_old = judged.rms_with(applied)
            r_new = judged.rms_with(coeffs)
            z = judged.paired_gain_z(applied, coeffs)
            self.last_validation["wander"] = {
                "floor_dps": dict(zip("xyz", g.floor.tolist(), strict=True)), "blocks": len(judged),
                "rms_current_dps": dict(zip("xyz", r_old.tolist(), strict=True)),
                "rms_new_dps": dict(zip("xyz", r_new.tolist(), strict=True)),
                "gain_z": round(z, 2), "need_z": WANDER_GAIN_Z}
            enough = float(np.sum(r_new**2)) < float(np.sum(r_old**2)) and z >= WANDER_GAIN_Z
        if refining and g is not None:
            one_axis = bool(np.any(rms_new <= (1.0 - self.cfg.validation["min_improvement"]) * rms_old))
            enough = enough or one_axis or g.widened
        worse_axes = [a for a, w in zip("xyz", worse, strict=True) if w]
        if refining and g is not None:
            gains = [a for a, w in zip("xyz", g.gains, strict=True) if w]
            self.last_validation["refinement"] = {"widened": g.widened, "worse_axes": worse_axes,
                                                  "gains": gains}
        if worse_axes:
            why = (f"validation: new set's held-out RMS {_dph(rms_new)} deg/h is worse than the held set's "
                   f"{_dph(rms_old)} deg/h on axis {'/'.join(worse_axes)}; not pushing")
        elif not enough:
            why = (f"validation: new set's held-out RMS {np.sqrt(new2) * DPH:.3g} deg/h (3 axes) does not "
                   f"improve enough on the current {np.sqrt(old2) * DPH:.3g} deg/h; not pushing")
            if "wander" in self.last_validation:
                why = why.replace("; not pushing", f" (nor significantly, beside the bias wander: "
                                  f"{self.last_validation['wander']['gain_z']:.1f} standard errors of "
                                  f"{WANDER_GAIN_Z:g}); not pushing")
        else:
            why = ""
        if why:
            self.last_validation["passed"] = False
            self._refused_why = why
            self._next_validation_at = int(self.learner.samples * 1.5) + 1
            if stage == "bias":
                log.info("unit %s: bias stage: %s", self.hello.serial, why)
                self.state, self.reason = State.COLLECTING, why
                self.learner.owe_bias = False  # refused on its merits: the full set may follow
                return
            # routine either way (a re-check while monitoring, or a first set that needs more samples):
            # INFO, so `journalctl -p warning` shows faults only (an operator's audit); status says why
            log.info("unit %s: %s", self.hello.serial, why)
            if self.validated_rms is not None:
                self.state = State.MONITORING
            else:
                self.state, self.reason = State.COLLECTING, why
            return
        self.last_validation["passed"] = True
        refused = self._unknown_terms.get(terms_id(list(proj.held_names)))
        if refused is not None:  # the unit said it cannot evaluate these terms: no version minted
            self.state, self.reason = State.COLLECTING, refused
            self._next_validation_at = int(self.learner.samples * 1.5) + 1
            return
        if self._retry is not None:  # a failed push of an earlier set is due again: no new version now
            self.state = State.COLLECTING
            self.reason = f"v{self._retry['version']} is pushed again first (round {self._retry['round']})"
            return
        why = check_set(list(proj.held_names), proj.held_dps)
        if why is not None:
            self.state, self.reason = State.COLLECTING, f"validated set not pushed: {why}"
            self._next_validation_at = int(self.learner.samples * 1.5) + 1
            log.warning("unit %s: %s", self.hello.serial, self.reason)
            return
        if now < self._store_retry_at:
            self.state = State.MONITORING if self.validated_rms is not None else State.COLLECTING
            self._bias_unsent(stage)
            return
        self._push_prediction = {k: _xyz_dph(v) for k, v in self.prediction.items()
                                 if k in PREDICTED_KEYS}
        infl = self.prediction.get("noise_inflation", np.ones(3))
        self._push_prediction["noise_inflation"] = np.round(infl, 3).tolist()
        if "unseen_share" in self.prediction:
            self._push_prediction["unseen_share"] = round(float(self.prediction["unseen_share"]), 4)
        self._push_prediction["stage"] = stage
        if kept:  # those axes hold the held set's rows: its own prediction, where its record has one,
            # with the bias movement left in place (a kept axis's bound was half its truth: an audit)
            held_left = self._held_info()[0]
            mask = np.array([a in kept for a in "xyz"])
            # (a bias stage's kept axis: the bias may have moved since; a refinement keeps the rows the
            # new set would have worsened, whose own figure stands)
            moved = np.nan_to_num(np.asarray(self.prediction.get("removes", np.zeros(3)), dtype=float)) \
                if stage == "bias" else np.zeros(3)
            for k in PREDICTED_KEYS:
                if k in self._push_prediction:
                    v = np.array([np.nan if x is None else x / DPH
                                  for x in self._push_prediction[k].values()], dtype=float)
                    v[mask] = 0.0 if k == "removes" else np.nan if held_left is None else \
                        np.hypot(held_left, moved)[mask]
                    self._push_prediction[k] = _xyz_dph(v)
            self._push_prediction["kept_axes"] = kept
        if (stage == "bias" and self.learner.cold_ready) or _constant_only(proj.held_names, proj.held_dps):
            # a constant alone, every other term 0 (a unit at one pose, a board at one temperature):
            # good where the unit was seen, unknown elsewhere. Its sphere figure said 1.02 deg/h where
            # the unit's drift over the sphere was 8.7/22.7/17.4 (a serial integrator's vehicle unit).
            # So at every later switch-on still at that pose: its bias stage and refinements, kept
            # from the held constant-only set, said 0.72 then 0.22 deg/h over the sphere where the
            # unit left 76/23/26 away from its pose (an integrator's CAN campaign). After the kept
            # axes: they had carried the held set's at-pose figure as their sphere one (a re-check)
            nan = _xyz_dph(np.full(3, np.nan))
            self._push_prediction.update(left_sphere=nan, bound=nan, expected=nan, constant_only=True)
        wrote_from, heard = time.monotonic(), self.unit_clock_s
        try:
            record = self._record(proj)
        except Exception as err:  # never push a set the store does not know
            first = self.store_error != str(err)  # one line per fault, not one per retry
            self.store_error = str(err)
            self._store_retry_at = now + self.STORE_RETRY_S
            self.state = State.MONITORING if self.validated_rms is not None else State.COLLECTING
            self.reason = (f"store unavailable: {err}; validated set not pushed, "
                           f"retrying every {self.STORE_RETRY_S:g} s")
            log.log(logging.ERROR if first else logging.DEBUG, "unit %s: %s", self.hello.serial, self.reason)
            self._bias_unsent(stage)
            return
        self.store_error = None
        self.learner.owe_bias = False  # recorded: pushed next, the stage is paid
        self.validated_rms = rms_new
        if stage == "bias":
            # judged in sample on a few blocks: the alarm's reference must hold what other poses and
            # later blocks will show (block noise, the stored terms' and the new bias's error). Its
            # in-sample residual counts up to BIAS_REF_EXCESS times that: beyond, the blocks held
            # what no bias explains (a step among them), which is not the set's to keep
            block_var = self.learner.residual_var() / max(self.acc.size, 1)
            left = np.nan_to_num(self.prediction.get("left_sphere", np.zeros(3)), posinf=0.0)
            expect = block_var + left**2
            self.validated_rms = np.sqrt(np.minimum(rms_new**2, self.BIAS_REF_EXCESS**2 * expect) + expect)
        took = time.monotonic() - wrote_from
        if took > self.SLOW_WRITE_S and np.isfinite(heard):
            # the messages of those seconds are still queued behind the samples: the unit may have
            # switched off and on meanwhile. Pushed at once, the last boot's set went to the new boot
            # 1.0 s after its switch-on and ran for 17 s (an operator's slow-disk audit). It goes when
            # the samples of the write's time are read, after any HELLO among them (a new session)
            self._push_due = {"version": record["version"], "names": list(proj.held_names),
                              "coeffs": proj.held_dps, "heard": heard + took}
            self.state = State.PUSHING
            self.reason = (f"v{record['version']} recorded in {took:.1f} s (a slow store): pushed once the "
                           "unit's samples of that time are read")
            log.info("unit %s: %s", self.hello.serial, self.reason)
            return
        self.start_push(record["version"], list(proj.held_names), proj.held_dps, now)

    def _record(self, proj: Projection) -> dict[str, Any]:
        """The record of the set the unit will hold; the learnt rest (if any) in ``host_remainder``."""
        idx = [self.names.index(n) for n in proj.held_names]
        rec = CalibrationRecord(
            serial=self.hello.serial, version=0, terms=list(proj.held_names),
            coefficients_dps=proj.held_dps.tolist(),
            # the store writes undetermined (inf) as null
            uncertainty_dps=self.learner.uncertainty[:, idx],
            host_remainder={} if proj.exact else proj.record(self.names),
            identifiable=self.learner.identifiable(),
            stats={"samples": self.samples, "still_samples": self.still_samples,
                   "trained_samples": self.learner.samples, "validation": self.last_validation,
                   "predicted_drift_dph": self._push_prediction,
                   "warm_started_from": self.warm_started_from, "resumed_from": self.resumed_from,
                   "bias_steps": self.bias_steps,  # found this switch-on: the set is learnt after them
                   # the range the set's temperature terms were learnt over (this and earlier
                   # switch-ons' merged; a bias stage keeps the held set's terms, so its range), and
                   # the information on those terms for the next switch-on with the range it spans
                   # (learner.py)
                   "temp_range_c": self._set_range(proj),
                   "temp_information": self.learner.temp_information(),
                   "temp_information_range_c": self.temp_range()},
            session={"boot_count": self.hello.boot_count, "fw": self.hello.fw_version},
            push={"status": "pending"},
        )
        rec = self.store.add(rec, min_version=self.version_floor())
        return {"version": rec.version}

    def _set_range(self, proj: Projection) -> list[float] | None:
        """The range [degC] the set about to be recorded holds its temperature terms for: a bias stage's
        are the held set's, and so are those of a set that keeps the held rows on an axis; so is its
        range. Recorded as the range seen, a year of bias stages widened it to -25..70 degC over terms
        learnt at 19..38, and the refinement that the wider range calls for never came: 17.6/20.5/2.5
        deg/h left in a winter warm-up where no temperature terms left 8.7/3.4/16.3 (a fleet engineer's
        year of switch-ons; its re-check found the kept rows and a held set whose ack was lost)."""
        rng = self.temp_range()
        held = self._held_info()[1]
        if held is None:
            return rng
        if self.last_validation.get("stage") == "bias":
            return [held[0], held[1]]
        applied, idx = self._applied_coeffs(), temp_indices(list(self.names))
        new = np.asarray(proj.embedded_dps, dtype=float)
        if applied is not None and idx and new.shape == applied.shape \
                and np.any(np.all(new[:, idx] == applied[:, idx], axis=1)):
            return [held[0], held[1]]  # an axis keeps the held set's temperature terms
        return rng

    def temp_range(self) -> list[float] | None:
        """The temperature range [degC] the learnt set covers: this session's still samples, merged with
        the range of the earlier switch-ons whose information the learner holds (None: no temp term)."""
        rngs = [r for r in (self.temp_seen, self.learner.prior_range) if r is not None]
        if not rngs:
            return None
        return [min(r[0] for r in rngs), max(r[1] for r in rngs)]

    def version_floor(self) -> int:
        """The lowest version a new set may take: above the one the unit holds (it may not be ours)."""
        return self.applied.version + 1 if self.applied is not None else 0

    # -- push ---------------------------------------------------------------------------------
    def start_push(self, version: int, names: list[str], coeffs: np.ndarray, now: float,
                   retry_round: int = 0) -> str | None:
        """Push a set (a validated one, a rollback or a file); the unit applies it whole or not.

        Returns None when the push started, else why it was refused (then nothing was sent, the
        session keeps its state, and the record's push status becomes 'refused')."""
        if self.push is not None:
            return f"v{self.push.write.version} is being pushed"
        try:
            why = check_set(list(names), coeffs)
            if why is None and not self.caps.holds(list(names)):
                why = f"the unit ({self.caps.kind}) cannot hold the terms {list(names)}"
            if why is None:
                coeffs = np.asarray(coeffs, dtype=np.float64)
                write = CoeffWrite(version, terms_id(names), tuple(tuple(map(float, r)) for r in coeffs))
        except Exception as err:  # an encoding the protocol refuses
            why = str(err)
        if why is not None:
            log.error("unit %s: push of v%d refused: %s", self.hello.serial, version, why)
            self.last_push = {"version": version, "status": "refused", "reasons": [why], "utc": utc_now()}
            try:  # only a record that was never sent is marked: an acked one keeps its history true
                rec = self.store.get(self.hello.serial, version)
            except Exception:
                rec = None
            if rec is not None and rec.push.get("status") == "pending":
                self._store_push(version, dict(self.last_push), now)
            return why
        self._pending = (list(names), coeffs)
        if self._blind is None or self._blind[1] is not None:  # a window still open keeps its start
            start = self.unit_clock_s if self._blind is None else min(self._blind[0], self.unit_clock_s)
            self._blind = [start, None]
        self._retry, self._retry_round = None, retry_round  # this push supersedes a pending retry
        self.state = State.PUSHING
        self.reason = f"pushing v{version}"
        # an autopilot answers a push later than our protocol's unit (capabilities.ack_within_s)
        ack_s = max(self.cfg.push["ack_timeout_s"], self.caps.ack_within_s or 0.0)
        self.push = PushTransaction(write, self._send, now, ack_s, self.cfg.push["retries"],
                                    quiet=retry_round >= 2)
        return None

    def _after_push(self, now: float) -> None:
        if self.push is None or not self.push.finished:
            return
        result = self.push.result
        if result is None:
            return
        version = self.push.write.version
        self.push = None
        self.last_push = {"version": version, **result.as_dict(), "utc": utc_now()}
        if self._push_prediction:
            self.last_push["predicted_drift_dph"] = self._push_prediction
            self._push_prediction = {}
        if result.status == "acked":
            # which switch-on took it, and when on the unit's clock [s]: a daemon restarted in the same
            # switch-on resumes from this record instead of calibrating the switch-on again (same_boot)
            self.last_push["unit"] = {"boot_count": self.hello.boot_count, "time_s": self.unit_clock_s}
        if result.status == "acked":
            op = self._operator_push
            # whose set it is, for a daemon restarted within this switch-on (same_boot); None clears
            # a rollback's mark when the daemon itself pushes that version again
            self.last_push["operator"] = op[1] if op is not None and op[0] == version else None
        if result.status == "acked" and self.caps.reboot_required:
            self.last_push["reboot_required"] = True  # in the store record of the push too
        if result.status == "acked" and self.caps.board_rotation is not None:
            self.last_push["board_rotation"] = dict(self.caps.board_rotation)  # the frame it was written in
        self._store_push(version, dict(self.last_push), now)
        if result.status == "acked":
            proj, self._projection = self._projection, None
            self.host_remainder = None if proj is None or proj.exact else proj.record(self.names)
            if self.caps.reboot_required:  # PX4 with TC_G_ENABLE off at boot (docs/mavlink.md)
                self.reboot_needed = {"version": version, "why": f"the unit ({self.caps.kind}) applies "
                                      "a pushed set only after its next reboot"}
                log.warning("unit %s: v%d is held; it takes effect at the unit's next reboot",
                            self.hello.serial, version)
            if (self.last_push.get("predicted_drift_dph") or {}).get("stage") == "full":
                self._range_pushed = self.temp_seen  # a widening counts from here (_gate)
            self.state = State.APPLIED  # the samples switch to the new set at the ack (see feed)
            self._held_has_north = False
            self._range_naks = 0
            log.info("unit %s: v%d applied and read back", self.hello.serial, version)
            self._watch_afresh()
            # the held-out blocks are kept: a refinement is validated over the whole range seen (their
            # raw rate does not depend on the set the unit applied)
            self.state = State.MONITORING
            self.reason = f"monitoring v{version}"
            self._next_validation_at = 2 * self.learner.samples + 1
        else:
            op = self._operator_push
            if op is not None and op[0] == version and not result.transient and self.operator_hold:
                # the unit refused the operator's set for good: it keeps its own, and holding the
                # daemon's pushes back for a set nobody holds left it on an old set (an audit: 119 deg/h)
                log.info("unit %s: the operator's v%d was not taken (%s): the daemon's own pushes resume",
                         self.hello.serial, version, result.status)
                self.operator_hold = None
            # a NAK is the unit's own word; after a timeout it may hold either set (it held v8 while
            # this said it kept its set: an integrator's fault campaign, F4)
            holds = "the unit keeps its set" if result.status == "nak" else \
                "its read-back says which set it holds"
            self.reason = f"push of v{version} failed ({result.status}); {holds}"
            transient = result.transient
            names = self._pending[0]
            tid = terms_id(names)
            held = self.applied is not None and self.applied.terms_id == tid
            if result.nak_reason == int(NakReason.UNKNOWN_TERMS) and held \
                    and self._contradicted < self.CONTRADICTED_MAX:
                # the unit reports holding this very term set: its refusal contradicts itself (a glitch,
                # a unit busy rebuilding its table). Taken as final, it left the unit on the last boot's
                # set, 105 deg/h off, for the whole switch-on (an integrator's audit): tried again
                self._contradicted += 1
                transient = True
                log.warning("unit %s: NAK UNKNOWN_TERMS to v%d for term set 0x%04X, which the unit reports "
                            "holding (v%d): taken as a passing refusal, tried again (%d of %d)",
                            self.hello.serial, version, tid, self.applied.version, self._contradicted,
                            self.CONTRADICTED_MAX)
            elif result.nak_reason == int(NakReason.UNKNOWN_TERMS):  # final: no new version would help
                self.reason = (f"the unit does not know term set 0x{tid:04X} ({len(names)} terms: "
                               f"{','.join(names)}): NAK UNKNOWN_TERMS to v{version}, so it keeps its set "
                               "and this set is not pushed again this session; configure estimator.terms "
                               "as a set in the unit's table (docs/protocol.md, section 4)")
                self._unknown_terms[tid] = self.reason
                log.error("unit %s: %s", self.hello.serial, self.reason)
            self._range_naks = self._range_naks + 1 if result.nak_reason == int(NakReason.OUT_OF_RANGE) else 0
            if self._range_naks >= self.RANGE_NAKS_MAX:
                # an autopilot that refuses one parameter refused every new set the same way, and each
                # became a stored version with three error lines (an integrator's audit: v1..v5 in 90 s)
                self.range_hold = (f"the unit refused {self._range_naks} sets in a row as out of range (NAK "
                                   f"OUT_OF_RANGE, last v{version}); no more sets are pushed this switch-on. "
                                   "Its log says which value it refused; `gyrocal recalibrate` or the next "
                                   "switch-on tries again")
                self.reason = self.range_hold
                log.error("unit %s: %s", self.hello.serial, self.range_hold)
            self._next_validation_at = int(self.learner.samples * 1.5) + 1
            self.state = State.COLLECTING
            if transient:  # BUSY, silence, link down: the same record again later
                rnd = self._retry_round + 1
                delay = min(self.RETRY_BACKOFF_S * 2.0 ** (rnd - 1), self.RETRY_BACKOFF_MAX_S)
                names, coeffs = self._pending
                self._retry = {"version": version, "names": names, "coeffs": coeffs, "round": rnd,
                               "at": now + delay}
                self.reason += f"; the same v{version} is tried again in {delay:.0f} s"
            self._forget_set()  # read back what the unit holds, don't assume it
            self._read_asks = 0
            self.request_read(now)

    VALIDATION_TRIM = 0.25
    """Validation compares the sets over the held-out blocks but this share, those that neither set
    explains (``BlockWindow.paired_rms``): a slow turn the still rule cannot see, as for the alarm."""

    ALARM_TRIM = 0.25
    """The drift alarm's RMS leaves out this share of the monitor's blocks, those with the largest
    residual: a drift the set leaves is in every block, while a slow turn taken for rest (one the still
    rule cannot see: model/still.py, ``k_turn``) is in the block or two of each move. A vehicle rolling
    0.06 deg between rests in 1.1 s raised alarms of 28-87 deg/h where the unit left under 4 (a fleet
    engineer's road drives; 44-80 deg/h in process)."""

    WATCH_BLOCKS = 8
    """Still blocks of a warm switch-on after which the held set is watched, before any push."""

    def _watch_held(self) -> None:
        """A warm switch-on whose held set needs no push (its bias has not moved) had no alarm at all: a
        100 deg/h step of the bias went unseen and the sets that followed averaged it in, x 61, 30, then
        15 deg/h off with the alarm off (an outside re-check: 51-55 deg/h on a road drive). Once
        WATCH_BLOCKS blocks are in, the held set's residual over them is the alarm's reference until a
        set of this session is validated (the alarm floor below it; this switch-on's bias move, if any,
        is in it, and its bias stage pushes soon)."""
        if self.validated_rms is not None or self._watch_rms is not None or not self.learner.has_prior \
                or len(self.monitor) < self.WATCH_BLOCKS:
            return
        held = self._applied_coeffs()
        if held is None or _constant_only(self.names, held):
            return
        self._watch_rms = self.monitor.rms_with(held, self.ALARM_TRIM)

    def _watch_afresh(self) -> None:
        """The unit holds another set: the drift monitor starts again on it, and so does its alarm,
        which was about the set before. Kept until the new set's first judgement (ALARM_MIN_BLOCKS,
        4 s of rest), status said `alarm: true` for 5.5-5.7 s after the set that took a bias step
        out was acked, while the unit was left 0.3-2 deg/h (an outside re-check, F5)."""
        self.monitor.clear()
        self.alarm = self.alarm_beyond_range = False

    def _check_alarm(self) -> None:
        ref = self.validated_rms if self.validated_rms is not None else self._watch_rms
        if ref is None or len(self.monitor) < self.ALARM_MIN_BLOCKS:
            return
        applied = self._applied_coeffs()
        rms = self.monitor.rms_with(applied, self.ALARM_TRIM)  # None: the unit's output as sent
        limit = np.maximum(ref * self.cfg.monitor["alarm_ratio"], self.cfg.monitor["alarm_floor_dps"])
        alarm = bool(np.any(rms > limit))
        rng, temp = self._held_info()[1], self._context.get("temp")
        if alarm and rng is not None and temp is not None and not rng[0] - 1.0 <= temp <= rng[1] + 1.0:
            # beyond the range the held set was learnt over, its residual grows as expected, and the
            # refinement that widens it is due: a WARNING there fired in 7 of 8 healthy warm-ups of an
            # autopilot and taught operators to ignore it (an integrator's audit)
            if not self.alarm_beyond_range:
                log.info("unit %s: residual %s deg/h above the alarm's %s deg/h at %.1f degC, beyond the "
                         "held set's %.1f..%.1f degC: a refinement is due, no alarm", self.hello.serial,
                         "/".join(f"{v:.3g}" for v in rms * DPH), "/".join(f"{v:.3g}" for v in limit * DPH),
                         temp, rng[0], rng[1])
            self.alarm_beyond_range, alarm = True, False
        else:
            self.alarm_beyond_range = False
        if alarm and self.alarm:
            self._relearn_after_alarm()  # an alarm that outlasts RELEARN_MIN_S starts learning again then
        elif alarm:
            # in deg/h, as every other drift figure of the log (an operator's soak found them mixed); the
            # window's RMS still holds the blocks from before a step (8.1 deg/h for a 21.6 deg/h step,
            # a fleet engineer's check): the newest rests' figure says what the unit is left with now
            recent = self.monitor.since(self._t_last - self.ALARM_RECENT_S).rms_with(applied)
            # an alarm again on a set already said to be off at these poses, with learning going on past
            # it (_relearn_after_alarm): its detail, not a new fault; it was a WARNING after that line
            # (an integrator's re-check, rc35 N2)
            known = self.applied is not None and self.applied.version in self._alarm_kept
            log.log(logging.INFO if known else logging.WARNING,
                    "unit %s: drift alarm: residual %s deg/h exceeds %s deg/h (the last %g s of rests: "
                    "%s deg/h)", self.hello.serial, "/".join(f"{v:.3g}" for v in rms * DPH),
                    "/".join(f"{v:.3g}" for v in limit * DPH), self.ALARM_RECENT_S,
                    "/".join(f"{v:.3g}" for v in recent * DPH))
            self._relearn_after_alarm()
        self.alarm = alarm

    ALARM_MIN_BLOCKS = 8
    """The alarm is judged from this many monitor blocks on (4 s of rest at 0.5 s blocks), when its
    trim leaves out 2: with 4-7 a turn too slow for the still rule spoilt 2 of them and gave a false
    alarm about 6 s after switch-on (87.4/26.6/3.66 deg/h where the unit left 1.60/0.47/0.30, an
    outside re-check's road drive)."""

    ALARM_RECENT_S = 2.0
    """The alarm's line also gives the residual of the rests of this many seconds [s] before it."""

    RELEARN_MIN_S = 30.0
    """Unit time [s] between two restarts of learning on a drift alarm (``_relearn_after_alarm``)."""
    RELEARN_NEWER_S = 10.0
    """The same once the unit holds a newer set than at the last restart (its bias stage was pushed)."""

    BIAS_REF_EXCESS = 2.0
    """A bias stage's in-sample residual counts in the drift alarm's reference up to this many times
    what the stage is expected to leave (block noise, the terms' and the bias's error). A 100 deg/h step
    0.5-1.5 s before a warm switch-on's first bias stage, or in the 18 s before a cold unit's constant
    alone at one pose, was averaged into the set, whose in-sample residual (41-80 deg/h) became the
    alarm's baseline: the unit was left 21.6-93.5 deg/h off with `alarm: false` for the rest of the
    switch-on (an outside re-check)."""

    STEP_WINDOW_BLOCKS = 1024
    """Still blocks of the data being learnt from that the bias step check looks at (8.5 min at 0.5 s)."""
    STEP_RESTARTS_MAX = 3
    """Bias steps per switch-on that start learning again: a walking bias (a continuum of small steps)
    that passed the check's tests could otherwise keep a first set from ever being pushed."""
    def _unwatched(self) -> bool:
        """No drift alarm can start learning again: no set of this session is held (nor watched), or
        the unit holds a constant alone, which an alarm does not relearn (``_relearn_after_alarm``).
        A cold unit at one pose whose bias stepped 2 s before its constant was pushed raised the alarm,
        and was left 95 deg/h off with it (in process). Checked every 2 blocks whatever watched the
        drift, a warm-up from 5 degC was taken for a 16 deg/h step 4 s in, and learning started again
        without the first seconds of the warm-up its rate terms needed (rank 12 of 13 at the end:
        tests/test_daemon_refine.py); a held set watched over blocks holding a step 2.5-3 s in waits
        for the next validation instead (8.5-15 s over 10 deg/h with the alarm off, in process)."""
        if self.validated_rms is None and self._watch_rms is None:
            return True
        held = self._applied_coeffs()
        return held is not None and _constant_only(self.names, held)

    EARLY_BLOCKS = 3
    """A step with fewer still blocks than this before it is said to be a step or the unit settling:
    one block before a step is enough to place it (stepcheck.py), and a unit's turn-on transient
    looks the same (a flicker unit's y: 17 deg/h at 1.1 s, benchmarks/bench_wander_gate.py seed 4).
    Learning starts again after it either way, which loses those blocks alone."""

    def _step_found(self, every_block: bool = False) -> bool:
        """A step of the bias in the data the estimator is learning from (stepcheck.py): learning
        starts again after it, from the set the unit holds (as after a drift alarm) or, with none, from
        nothing; True if so. Checked as each 2 blocks come while no alarm can start learning again
        (``_unwatched``), and before every validation, a bias stage's too (``every_block``): a set
        learnt across the step takes the average of the two biases, and its residual, which holds the
        step, would become the drift alarm's reference (an outside re-check: a cold unit at one pose, a
        100 deg/h step 17 s before its constant was pushed, left 72.9 deg/h off with the alarm off for
        238 s, to the end of its run). A step with fewer than EARLY_BLOCKS still blocks before it may
        be the unit settling after switch-on: its line says so."""
        if len(self.bias_steps) >= self.STEP_RESTARTS_MAX:
            return False
        if not every_block and self._learnt_n < self._step_checked + 2:
            return False
        self._step_checked = self._learnt_n
        step = find_step(list(self.learnt.blocks), floor_dps=float(self.cfg.monitor["alarm_floor_dps"]))
        if step is None:
            return False
        self.bias_steps.append({"axis": "xyz"[step.axis], "dph": round(step.dps * DPH, 2),
                                "unit_time_s": round(step.t_s, 2), "z": round(step.z, 1),
                                "blocks_before": step.before})
        held = self._applied_coeffs()
        # from a warm start's set, or a set of this session: a cold unit's constant alone at one pose,
        # whose own bias stage then takes the step out at once (learning from nothing, it waited 60 s more)
        if self.applied is not None and held is not None \
                and (self.learner.has_prior or self.last_push.get("status") == "acked") \
                and self._learn_again_from_held(self.applied.version, held):
            restart = f"from v{self.applied.version}, the set it holds"
        else:
            restart = "from nothing"
            self._learn_again(self.learner.fresh())
            # its bias stage (a cold unit's constant alone) is due again: a step found as that stage was
            # validated would leave it marked done, and the constant would not be learnt again
            self._bias_pushed, self._bias_partial = False, False
        self.reason = (f"the {'xyz'[step.axis]} bias stepped by {step.dps * DPH:+.3g} deg/h at about unit "
                       f"time {step.t_s:.1f} s: learning starts again {restart}")
        early = "" if step.before >= self.EARLY_BLOCKS else \
            f", {step.before} before it: a step, or the unit still settling"
        log.warning("unit %s: %s (%.0f standard errors, %d still blocks after it%s; step %d of at most %d "
                    "this switch-on)", self.hello.serial, self.reason, step.z, step.after, early,
                    len(self.bias_steps), self.STEP_RESTARTS_MAX)
        self.state = State.COLLECTING
        return True

    def _relearn_after_alarm(self) -> None:
        """A drift alarm: the unit's drift has moved since its set was validated (a shock, a step of its
        bias). Learning on every sample since switch-on, the next set averaged the old bias with the new:
        it took 56 of a 100 deg/h step on x, its held-out RMS became the alarm's reference, and the unit
        was left 46 deg/h off with the alarm off and status predicting 0.3 (an outside re-check). So
        learning starts again from the set the unit holds, as at a warm switch-on: its bias stage on the
        samples from here, then a full set when they support one. Not for a constant alone (off at other
        poses by design: docs/operations.md), and once per RELEARN_MIN_S, or RELEARN_NEWER_S once the
        unit holds a newer set than at the last restart: a second step 12 s after the first, once the
        first's bias stage was pushed, waited out the 30 s while a full set learnt over it was pushed,
        leaving x 30, then 15 and 7.5 deg/h off with the alarm off. The floor bounds the pushes a run
        of false alarms could cause."""
        held = self._applied_coeffs()
        if held is None or _constant_only(self.names, held) or self.applied is None:
            return
        if self._relearned_from is not None and self.applied.version != self._relearned_from \
                and self.applied.version in self._relearn_stages and not self._relearning:
            # the alarm is back on the bias stage the last restart pushed: a bias does not explain it (the
            # held terms are off at the poses since), and what does is learnt from the samples since that
            # restart, which a new restart would throw away. A unit whose gravity terms had moved 10-30
            # deg/h since its held set got a bias stage after each alarm, 12-19 pushes in 100-200 s, and
            # was left 14-65 deg/h off (an integrator's fault campaign, rc33 W0/W1/W7). A second step of
            # the bias is still placed: the step check looks at those samples as each 2 blocks come (it
            # restarts learning)
            if self._step_found():
                return
            if self.applied.version not in self._alarm_kept:
                self._alarm_kept.add(self.applied.version)
                log.info("unit %s: the drift alarm is back on v%d, the bias stage of the last restart, and "
                         "no step of the bias explains it: its terms are off at these poses; learning goes "
                         "on towards a full set", self.hello.serial, self.applied.version)
            return
        wait = self.RELEARN_MIN_S if self.applied.version == self._relearned_from else self.RELEARN_NEWER_S
        if self._t_last - self._relearned_at < wait:
            return
        if self._learn_again_from_held(self.applied.version, held):
            log.info("unit %s: learning starts again from v%d, the set it holds: its bias stage on the "
                     "samples from the alarm on", self.hello.serial, self.applied.version)

    def _learn_again_from_held(self, version: int, held: np.ndarray) -> bool:
        """Learning starts again from the set the unit holds (v``version``, ``held`` in this session's
        term order), as at a warm switch-on: its bias stage on the samples from here is due. False
        (nothing changed) when that set cannot be a learner's prior. For a drift alarm and a bias step
        alike (``_relearn_after_alarm``, ``_step_found``)."""
        learner = Learner(self.cfg, self._held_prior(version, held, True)[0], self.rate_hz)
        if learner.prior is None:
            return False
        self._learn_again(learner)
        self._relearned_at, self._relearned_from = self._t_last, version
        self._bias_pushed, self._bias_partial, self._relearning = False, False, True
        return True

    def _applied_coeffs(self) -> np.ndarray | None:
        """The unit's set in this session's term order (a held subset is padded with zeros), or None if
        it holds terms this session does not learn (or none)."""
        a = self.applied
        if a is None or not set(a.names) <= set(self.names) or a.coeffs_dps.shape != (3, len(a.names)):
            return None
        if tuple(a.names) == tuple(self.names):
            return a.coeffs_dps
        out = np.zeros((3, len(self.names)))
        out[:, [self.names.index(n) for n in a.names]] = a.coeffs_dps
        return out

    # -- status -------------------------------------------------------------------------------
    def _held_now(self) -> AppliedSet | None:
        """The set the unit holds: an acked set from its ack on, though the samples switch to it only
        from the first one after the ack. Status said `applied: v7` for 14 s after v8 was acked and
        read back, while the unit fell silent (an integrator's fault campaign, F4)."""
        return self._switch[0] if self._switch is not None else self.applied

    def status(self) -> dict[str, Any]:
        ok, why = self.learner.converged
        held = self._held_now()
        return {
            "state": self.state.value,
            "reason": self.reason,
            "unit": {"serial": self.hello.serial, "boot_count": self.hello.boot_count,
                     "fw": self.hello.fw_version, "rate_hz": getattr(self.hello, "rate_hz", 0)},
            "applied": None if held is None else {"version": held.version, "terms_id": held.terms_id},
            "samples": self.samples, "still_samples": self.still_samples,
            "trained_samples": self.learner.samples, "dtemp_inexact_samples": self.inexact_samples,
            "push_blind_samples": self.blind_samples,
            "stray_acks": self.stray_acks,
            "terms": self.names,
            "coefficients_dps": finite_or_none(self.learner.coefficients),
            "uncertainty_dps": finite_or_none(self.learner.uncertainty),
            "identifiable": self.learner.identifiable(),
            "converged": ok, "converged_reason": why,
            "validation": self.last_validation,
            "monitor_rms_dps": dict(zip("xyz", finite_or_none(
                self.monitor.rms_with(self._applied_coeffs(), self.ALARM_TRIM))[0], strict=True)),
            "alarm": self.alarm,
            "alarm_beyond_range": self.alarm_beyond_range,
            "bias_steps": self.bias_steps,
            "last_push": self.last_push,
            "warm_started_from": self.warm_started_from,
            "resumed_from": self.resumed_from,
            "operator_hold": self.operator_hold,
            "range_hold": self.range_hold,
            "unit_set": self.agreement,
            "faults": {"refused_reports": self.refused_reports, "send_failures": self.send_failures,
                       "coeff_read_asks": self._read_asks,
                       "store": ("ok" if self.store_error is None
                                 else f"store unavailable: {self.store_error}"),
                       "unrecorded_push_results": len(self.unrecorded),
                       "retry": None if self._retry is None else {"version": self._retry["version"],
                                                                   "round": self._retry["round"]}},
            "poses_seen": len(self.poses),
            "earth": None if self.earth is None else self.earth.status(),
            "unit_caps": self.caps.as_dict(),
            "reboot_needed": self.reboot_needed,
            "host_remainder": self.host_remainder,
            "next_set_waits": self.next_set_waits if self.state is State.MONITORING else None,
            "predicted_drift_dph": self._status_prediction(),
        }

    def _status_prediction(self) -> dict[str, Any]:
        """The live prediction for status: a constant alone (a cold start that stopped learning) holds
        where the unit was seen, so no sphere figure is given, as in its push record (status said
        1.02 deg/h over the sphere where a vehicle unit's drift was 8.4/21.7/18.5: an audit)."""
        out = {k: (_xyz_dph(v) if k in PREDICTED_KEYS else v)
               for k, v in self.prediction.items() if k != "gate"}
        coeffs = self.learner.coefficients
        if out and (self.learner.cold_ready or (coeffs is not None and _constant_only(self.names, coeffs))):
            nan = _xyz_dph(np.full(3, np.nan))
            out.update(left_sphere=nan, bound=nan, expected=nan, constant_only=True)
        return out


def _range(r: tuple[float, float] | None) -> str:
    return "?" if r is None else f"{r[0]:.1f}..{r[1]:.1f}"


def _axes(mask: np.ndarray) -> str:
    """The axes a (3,) bool mask selects, as "x/z"."""
    return "/".join(a for a, m in zip("xyz", mask, strict=True) if m)


def _dph(v: np.ndarray) -> str:
    """A per-axis figure [deg/s] as deg/h text for log lines and reasons."""
    return "/".join(f"{x * DPH:.3g}" for x in np.asarray(v, dtype=float))


def _constant_only(names: Any, coeffs: Any) -> bool:
    """Whether a set [deg/s] is its constant alone, every other term exactly 0: what a unit seen at
    one pose (or one temperature) gets, never a fit that found those terms (a fit is never exactly 0)."""
    c = np.asarray(coeffs, dtype=float)
    names = list(names)
    if "1" not in names or c.ndim != 2 or c.shape[1] != len(names) or len(names) < 2:
        return False
    others = [i for i, n in enumerate(names) if n != "1"]
    return bool(np.all(c[:, others] == 0.0))


def _xyz_dph(v: np.ndarray) -> dict[str, float | None]:
    """A per-axis figure [deg/s] as {x, y, z} in deg/h for status and records (inf/NaN as None)."""
    v = np.asarray(v, dtype=float)
    return {a: (float(x) * DPH if np.isfinite(x) else None) for a, x in zip("xyz", v, strict=True)}
