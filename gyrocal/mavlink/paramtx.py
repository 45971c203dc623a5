"""The parameter push and read as pure logic: PARAM_SET, its PARAM_VALUE echo, retries, read-back.

Why a state machine of its own: writing an autopilot's compensation is the one moment we change the
vehicle, and each failure (a lost echo, a rejected value, a reboot, silence) must end in a known
state. The guarantee is ours (docs/protocol.md's atomic apply) carried over to parameters, which
the autopilot applies one by one:

    read context -> ENABLE=0 -> write each coefficient (confirm each echo) -> read all back (verify)
    -> ENABLE=1 -> read the whole set back

The coefficients are written in the autopilot's sensor frame, rotated by the board rotation read in
the context (profiles.py). The verify read and the final read include the rotation parameters again:
a rotation changed during the push (a ground station writing SENS_BOARD_ROT/AHRS_ORIENTATION) would
make the written set wrong, so it is then never enabled (verify), or disabled again (final read),
and the push fails naming the change.

With compensation disabled the autopilot never evaluates a half-written set (PX4 reloads TC_Gn_*
only while TC_G_ENABLE=1; ArduPilot's correct_sensor returns at once unless ENABLE=1). A failure
after ENABLE=0 restores the previous coefficients and re-enables them only when every one is
confirmed; otherwise compensation stays off. The unit therefore holds the old set, the new one, or
none: never part of one.

Pure: no I/O, no threads. ``send`` receives :class:`ParamSet` / :class:`ParamRead`; time comes in as
``now`` [s, monotonic], so tests drive it deterministically.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from gyrocal.mavlink.profiles import Profile, decode_param, encode_param
from gyrocal.protocol.messages import NakReason

log = logging.getLogger("gyrocal.mavlink.push")


@dataclass(frozen=True)
class ParamSet:
    """Host -> autopilot PARAM_SET; ``wire`` is the encoded float (see ``encode_param``)."""

    name: str
    wire: float
    ptype: int


@dataclass(frozen=True)
class ParamRead:
    """Host -> autopilot PARAM_REQUEST_READ by name (param_index = -1)."""

    name: str


@dataclass
class _Op:
    name: str
    value: float | None = None  # None: read
    optional: bool = False  # a read some firmware does not answer (Profile.optional): skipped then


class OpRunner:
    """Runs parameter reads and writes one at a time, each confirmed by its PARAM_VALUE.

    A write is confirmed when the echo's value equals the value sent (as the autopilot stores it);
    an echo with another value is a rejection (the autopilot clamped or refused it) and stops the
    run. Silence for ``timeout_s`` resends the same request (PARAM_SET is idempotent), at most
    ``retries`` times in all.

    ``gate(now)``, when given, must say True before a write leaves (the first or a resend): the
    link's proof that the autopilot's clock ran on since its last answer. A write held longer than
    ``hold_max_s`` ends the run with an error, since nothing then tells whether it rebooted.
    """

    def __init__(
        self, profile: Profile, send: Callable[[object], None], timeout_s: float, retries: int,
        gate: Callable[[float], bool] | None = None, hold_max_s: float = 5.0,
    ) -> None:
        self.profile, self.send = profile, send
        self.gate, self.hold_max_s = gate, hold_max_s
        self._held: tuple[bool, float] | None = None  # a request the gate holds: (first, since)
        self.types = profile.types()  # grows with extra_context() parameters as they are asked for
        self.timeout_s, self.retries = timeout_s, retries
        self.values: dict[str, float] = {}
        self.error: str | None = None
        self.rejected = False
        self.held_out = False  # the error is the gate's: no IMU sample, not a missing parameter
        self.resends = 0
        self._ops: list[_Op] = []
        self._tries = 0
        self._deadline = 0.0

    @property
    def done(self) -> bool:
        return not self._ops or self.error is not None

    def start(self, ops: list[_Op], now: float) -> None:
        self._ops, self.error, self.rejected, self.held_out = list(ops), None, False, False
        self._held = None
        self._issue(now, first=True)

    def read_extra(self, now: float) -> bool:
        """After a full read: ask for the profile's extra_context parameters not read yet (once).
        Returns True when it started reads (the caller waits for ``done`` again)."""
        extra = [q for q in self.profile.extra_context(self.values)
                 if q.name not in self.values and q.name not in self.profile.absent]
        if not extra or self.error:
            return False
        for q in extra:
            self.types[q.name] = q.ptype
        self.start([_Op(q.name, optional=q.name in self.profile.optional) for q in extra], now)
        return True

    def _issue(self, now: float, first: bool) -> None:
        if not self._ops:
            return
        op = self._ops[0]
        if self.gate is not None and op.value is not None and not self.gate(now):
            # an autopilot that rebooted while a request was on its way must not get the next write
            # (a PX4 took the rest of a set into its new boot, acked, and applied none of it). Reads
            # change nothing: a reboot among them is caught by the next write's gate or the ack's.
            if self._held is None:
                self._held = (first, now)
            return
        self._held = None
        self._tries = 1 if first else self._tries + 1
        self._deadline = now + self.timeout_s
        if op.value is None:
            self.send(ParamRead(op.name))
        else:
            ptype = self.types[op.name]
            self.send(ParamSet(op.name, encode_param(op.value, ptype, self.profile.bytewise), ptype))

    def on_value(self, name: str, wire: float, ptype: int, now: float) -> None:
        value = decode_param(wire, self.types.get(name, ptype), self.profile.bytewise)
        if name in self.types:
            self.values[name] = value
        if self.done or name != self._ops[0].name:
            return
        op = self._ops[0]
        if op.value is not None and value != op.value:
            self.error = f"{name}: the autopilot answered {value!r} to a write of {op.value!r} (rejected)"
            self.rejected = True
            return
        self._ops.pop(0)
        self._issue(now, first=True)

    def tick(self, now: float) -> None:
        if self.done:
            return
        if self._held is not None:
            first, since = self._held
            if self.gate is not None and self.gate(now):
                self._issue(now, first)
            elif now - since > self.hold_max_s:
                self.held_out = True
                self.error = (
                    f"{self._ops[0].name}: no IMU sample for {now - since:.1f} s while the autopilot "
                    "answers parameters, so whether it rebooted cannot be told"
                )
            return
        if now < self._deadline:
            return
        if self._tries >= self.retries:
            op = self._ops[0]
            if op.optional and op.value is None:  # this firmware lacks it: not asked for again
                self.profile.absent.add(op.name)
                log.info("%s not answered: taken as absent on this firmware", op.name)
                self._ops.pop(0)
                self._issue(now, first=True)
                return
            what = "read" if op.value is None else "write"
            self.error = (
                f"{op.name}: no PARAM_VALUE after {self._tries} {what} request(s) (the autopilot "
                "went silent, or this firmware lacks the parameter)"
            )
            return
        self.resends += 1
        log.info("no PARAM_VALUE for %s within %.1f s; asking again", self._ops[0].name, self.timeout_s)
        self._issue(now, first=False)


class Phase(enum.Enum):
    READ_CONTEXT = "read_context"
    DISABLE = "disable"
    WRITE = "write"
    VERIFY = "verify"
    ENABLE = "enable"
    READ_BACK = "read_back"
    CONFIRM = "confirm"
    RESTORE = "restore"
    RESTORE_ENABLE = "restore_enable"
    DONE = "done"
    FAILED = "failed"


@dataclass
class PushOutcome:
    """How a push ended: ``params`` is the final read of the whole set (what the unit holds)."""

    ok: bool
    reason: str = ""
    nak: int = 0
    params: dict[str, float] = field(default_factory=dict)
    target: dict[str, float] = field(default_factory=dict)
    restored: bool = False


class ParamPush:
    """One push of Q (3, 4) [deg/s] valid over [tmin, tmax] degC. See the module docstring."""

    def __init__(
        self,
        profile: Profile,
        q_dps: np.ndarray,
        tmin: float,
        tmax: float,
        send: Callable[[object], None],
        now: float,
        *,
        timeout_s: float = 0.5,
        retries: int = 4,
        gate: Callable[[float], bool] | None = None,
        hold_max_s: float = 5.0,
        expect_rotation: Mapping[str, float] | None = None,
    ) -> None:
        self.profile = profile
        self.expect_rotation = None if expect_rotation is None else dict(expect_rotation)
        """The board rotation the set was learnt under (the link's HELLO): another one read in the
        context refuses the push before any write, since the set would be written in a wrong frame."""
        self.q = np.asarray(q_dps, dtype=np.float64)
        self.tmin, self.tmax = float(tmin), float(tmax)
        self.gate = gate
        self.io = OpRunner(profile, send, timeout_s, retries, gate, hold_max_s)
        self._confirm_since = 0.0
        self._read_again = False  # the final read-back was read a second time
        self.phase = Phase.READ_CONTEXT
        self.outcome: PushOutcome | None = None
        self.before: dict[str, float] = {}
        self.target: dict[str, float] = {}
        self.rotation: dict[str, float] = {}
        """The board rotation parameters the set was written for (read in the context)."""
        self._fail: tuple[str, int] | None = None
        self._restored = False
        self._extra_asked: set[Phase] = set()
        self.io.start([_Op(p.name) for p in profile.all_params()], now)

    @property
    def finished(self) -> bool:
        return self.outcome is not None

    def on_value(self, name: str, wire: float, ptype: int, now: float) -> None:
        if self.finished:
            return
        self.io.on_value(name, wire, ptype, now)
        self._advance(now)

    def tick(self, now: float) -> None:
        if self.finished:
            return
        if self.phase is Phase.CONFIRM:
            return self._confirm(now)
        self.io.tick(now)
        self._advance(now)

    def _confirm(self, now: float) -> None:
        """The set reads back whole: acked once the autopilot's clock is seen running after it (the
        gate), so a reboot in the last exchanges is never acked as the set applied."""
        if self.gate is None or self.gate(now):
            self.phase = Phase.DONE
            self.outcome = PushOutcome(True, "", 0, dict(self.io.values), self.target)
        elif now - self._confirm_since > self.io.hold_max_s:
            self.phase = Phase.FAILED
            self.outcome = PushOutcome(
                False,
                f"no IMU sample for {now - self._confirm_since:.1f} s after the final read-back, so "
                "whether the autopilot rebooted during the push cannot be told",
                int(NakReason.BUSY), dict(self.io.values), self.target,
            )

    def abort(self, reason: str) -> None:
        """The autopilot rebooted or the link went down: nothing more can be confirmed."""
        if not self.finished:
            log.error("push aborted in phase %s: %s", self.phase.value, reason)
            self.phase = Phase.FAILED
            self.outcome = PushOutcome(False, reason, int(NakReason.BUSY), dict(self.io.values), self.target)

    # -- phases ---------------------------------------------------------------------------------
    def _rotation_changed(self) -> str:
        """'' when the rotation read now equals the one the set was written for, else what changed."""
        now = {k: self.io.values.get(k) for k in self.profile.rotation_names(self.io.values)}
        if now == self.rotation:
            return ""
        return (
            f"the board rotation changed during the push ({self.rotation} -> {now}): the set was written "
            "for the old one"
        )

    def _advance(self, now: float) -> None:
        if not self.io.done:
            return
        err = self.io.error
        p = self.profile
        if (
            not err
            and self.phase in (Phase.READ_CONTEXT, Phase.VERIFY, Phase.READ_BACK)
            and self.phase not in self._extra_asked
        ):
            self._extra_asked.add(self.phase)  # e.g. CUST_ROTn_* once AHRS_ORIENTATION is known
            if self.io.read_extra(now):
                return
        if self.phase is Phase.READ_CONTEXT:
            if err:
                nak = NakReason.BUSY if self.io.held_out else NakReason.UNKNOWN_TERMS
                return self._finish(False, err, nak)
            self.before = dict(self.io.values)
            why = p.problem(self.before) or p.check_range(self.q, self.tmin, self.tmax)
            if why:
                return self._finish(
                    False, why, NakReason.OUT_OF_RANGE if "offset" in why else NakReason.UNKNOWN_TERMS
                )
            self.rotation = {k: self.before.get(k) for k in p.rotation_names(self.before)}  # type: ignore[misc]
            if self.expect_rotation is not None and self.rotation != self.expect_rotation:
                return self._finish(False, f"the board rotation changed since the autopilot said HELLO "
                                    f"({self.expect_rotation} -> {self.rotation}): the set was learnt in "
                                    "the old frame; nothing written", NakReason.BUSY)
            self.target = p.to_params(self.q, self.before, self.tmin, self.tmax)
            self._go(Phase.DISABLE, [_Op(p.enable.name, 0.0)], now)
        elif err and self.phase in (Phase.DISABLE, Phase.WRITE, Phase.VERIFY, Phase.ENABLE) and (
            self._rotation_changed()
        ):
            # the rotation moved (and its new parameters could not all be read): neither the new set
            # nor the old one fits the new frame, so compensation stays off
            self._fail = (self._rotation_changed(), int(NakReason.BUSY))
            log.error("push failed in phase %s: %s; compensation left off", self.phase.value, err)
            self._go(Phase.RESTORE_ENABLE, [], now)
        elif err and self.phase in (Phase.DISABLE, Phase.WRITE, Phase.VERIFY, Phase.ENABLE):
            self._fail = (err, int(NakReason.OUT_OF_RANGE if self.io.rejected else NakReason.BUSY))
            log.error("push failed in phase %s: %s; restoring the previous set", self.phase.value, err)
            self._go(
                Phase.RESTORE,
                [_Op(c.name, self.before[c.name]) for c in p.coeffs if c.name in self.before],
                now,
            )
        elif self.phase is Phase.DISABLE:
            self._go(Phase.WRITE, [_Op(k, v) for k, v in self.target.items()], now)
        elif self.phase is Phase.WRITE:
            rot = [_Op(k) for k in p.rotation_names(self.before) if k not in self.target]
            self._go(Phase.VERIFY, [_Op(k) for k in self.target] + rot, now)
        elif self.phase is Phase.VERIFY:
            bad = [k for k, v in self.target.items() if self.io.values.get(k) != v]
            moved = self._rotation_changed()
            if moved:
                # compensation is off (ENABLE=0 was confirmed): neither the new set nor the old one,
                # both written for the old rotation, is enabled again
                log.error("push stopped before enabling: %s; compensation left off", moved)
                self._fail = (moved, int(NakReason.BUSY))
                self._go(Phase.RESTORE_ENABLE, [], now)
            elif bad:
                self._fail = (f"read-back differs for {', '.join(bad)}", int(NakReason.OUT_OF_RANGE))
                self._go(
                    Phase.RESTORE,
                    [_Op(c.name, self.before[c.name]) for c in p.coeffs if c.name in self.before],
                    now,
                )
            else:
                self._go(Phase.ENABLE, [_Op(p.enable.name, 1.0)], now)
        elif self.phase is Phase.ENABLE:
            self._go(Phase.READ_BACK, [_Op(x.name) for x in p.all_params()], now)
        elif self.phase is Phase.READ_BACK:
            moved = self._rotation_changed()
            if err and not moved:
                return self._finish(False, f"final read-back: {err}", NakReason.BUSY)
            if moved:
                log.error("final read-back: %s; disabling compensation", moved)
                self._fail = (moved, int(NakReason.BUSY))
                self._go(Phase.RESTORE_ENABLE, [_Op(p.enable.name, 0.0)], now)
                return
            ok = p.is_enabled(self.io.values) and all(
                self.io.values.get(k) == v for k, v in self.target.items()
            )
            if not ok and not self._read_again:
                # an echo that came late (1-2 s) answers the read that follows it: read once more
                # before calling the set different (a spurious failure and CRC mismatch: an audit)
                self._read_again = True
                self._go(Phase.READ_BACK, [_Op(x.name) for x in p.all_params()], now)
                return
            if ok:
                self.phase, self._confirm_since = Phase.CONFIRM, now
                return self._confirm(now)
            self._finish(False, "the final read-back differs from the set written", NakReason.BUSY)
        elif self.phase is Phase.RESTORE:
            self._restored = err is None
            if err is None and self.before.get(p.enable.name) == 1.0:
                self._go(Phase.RESTORE_ENABLE, [_Op(p.enable.name, 1.0)], now)
            else:
                self._go(Phase.RESTORE_ENABLE, [], now)
        elif self.phase is Phase.RESTORE_ENABLE:
            self._restored = self._restored and err is None
            self.phase = Phase.FAILED
            extra = [_Op(x.name) for x in p.extra_context(self.io.values)]
            self.io.start([_Op(x.name) for x in p.all_params()] + extra, now)
        elif self.phase is Phase.FAILED:
            reason, nak = self._fail or ("push failed", int(NakReason.BUSY))
            self.outcome = PushOutcome(
                False, reason, nak, dict(self.io.values), self.target, restored=self._restored
            )

    def _go(self, phase: Phase, ops: list[_Op], now: float) -> None:
        self.phase = phase
        if phase in (Phase.RESTORE, Phase.RESTORE_ENABLE):
            self.io.gate = None  # putting the old set back is right on whichever boot hears it
        self.io.start(ops, now)
        if not ops:
            self._advance(now)

    def _finish(self, ok: bool, reason: str, nak: NakReason) -> None:
        self.phase = Phase.DONE if ok else Phase.FAILED
        self.outcome = PushOutcome(ok, reason, 0 if ok else int(nak), dict(self.io.values), self.target)


class _Job:
    """A run of requests on an OpRunner (``io``) with a step of its own after each answer or tick:
    the shape the link feeds PARAM_VALUEs and time to, besides ParamPush."""

    io: OpRunner

    @property
    def error(self) -> str | None:
        return self.io.error

    def _after(self, now: float) -> None:
        raise NotImplementedError

    def on_value(self, name: str, wire: float, ptype: int, now: float) -> None:
        self.io.on_value(name, wire, ptype, now)
        self._after(now)

    def tick(self, now: float) -> None:
        self.io.tick(now)
        self._after(now)


class ParamReadAll(_Job):
    """Read every parameter of a profile (COEFF_READ, and the context at a switch-on)."""

    def __init__(
        self,
        profile: Profile,
        send: Callable[[object], None],
        now: float,
        *,
        timeout_s: float = 0.5,
        retries: int = 4,
    ) -> None:
        self.profile = profile
        self.io = OpRunner(profile, send, timeout_s, retries)
        self.io.start([_Op(p.name) for p in profile.all_params()], now)
        self._extra_asked = False

    @property
    def finished(self) -> bool:
        return self.io.done

    def _after(self, now: float) -> None:
        if self.io.done and not self._extra_asked:
            self._extra_asked = True
            self.io.read_extra(now)  # e.g. CUST_ROTn_* once AHRS_ORIENTATION says a custom rotation

    @property
    def values(self) -> Mapping[str, float]:
        return self.io.values


class ParamRestore(_Job):
    """Write back the set an autopilot held before a push that a reboot cut short.

    Why: the push writes ENABLE = 0 first; cut by a reboot before its ENABLE = 1, the autopilot boots
    with its compensation off and part of the new coefficients, worse than before the push. The
    durable coefficients read in the push's context (``before``) are written back, each confirmed by
    its echo, and ENABLE = 1 only when all are: the old set again (with an ArduPilot's offsets of
    this boot), or (a write not confirmed) none.
    """

    def __init__(self, profile: Profile, before: Mapping[str, float], send: Callable[[object], None],
                 now: float, *, timeout_s: float = 0.5, retries: int = 4) -> None:
        self.profile = profile
        self.io = OpRunner(profile, send, timeout_s, retries)
        # the durable ones only: an ArduPilot's INS_GYROFFS were measured again at this boot
        durable = set(profile.durable)
        self._coeffs = [_Op(c.name, float(before[c.name])) for c in profile.coeffs
                        if c.name in before and c.name in durable]
        self._enabling = False
        self.ok = False
        self.io.start(self._coeffs, now)

    @property
    def finished(self) -> bool:
        return self.io.done and (self._enabling or self.io.error is not None)

    def _after(self, now: float) -> None:
        if self.io.done and self.io.error is None and not self._enabling:
            self._enabling = True
            self.io.start([_Op(self.profile.enable.name, 1.0)], now)
        if self._enabling and self.io.done and self.io.error is None:
            self.ok = True
