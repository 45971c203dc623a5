"""The coefficient push: write, wait for a matching ack, read back, with retries and timeouts.

Why a separate little state machine: the push is the one moment the daemon changes the unit, and
its failure modes (NAK, silence, an ack whose CRC does not match, a read-back that differs) must each
end in a recorded outcome, never in a half-known unit. The unit applies a set atomically (the
protocol's CRC-checked commit), so a failed push leaves the unit with its old set; after any
failure we read back what the unit holds rather than assume it.

Retry rules (issue 8):

- a NAK BUSY, a NAK BAD_CRC or INCOMPLETE (a transfer hit by noise), an ack that never came and a
  write the link could not send are transient: the write is tried again after a back-off that
  doubles from ``backoff_s`` (capped at ``backoff_max_s``) with +-25 % jitter, so a busy unit and a
  daemon never retry in lock-step; at most ``retries`` attempts;
- a NAK UNKNOWN_TERMS, OUT_OF_RANGE or BAD_LENGTH is final at once: the same bytes would be refused
  again;
- ``send`` raising (``LinkError``/``OSError``: the cable is out) never escapes: the attempt is counted,
  its reason recorded, and the transaction waits for its back-off like any other transient failure.
  A push whose every write failed to leave the host ends as ``link_down``.

The result says whether the failure was transient (``PushResult.transient``): the session re-pushes
the same record later rather than minting a new version (see session.py).

Pure logic: no threads and no I/O. ``send`` is a callable the engine gives; time comes in as
``now`` (monotonic s), so tests drive it deterministically.
"""

from __future__ import annotations

import enum
import logging
import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gyrocal.errors import ConfigError, ProtocolError
from gyrocal.protocol.messages import (
    MAX_TERMS,
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffWrite,
    NakReason,
    coeff_set_crc,
)
from gyrocal.protocol.termsets import names_for, terms_id

log = logging.getLogger("gyrocal.push")

MAX_PUSH_COEFF_DPS = 10.0
"""The largest coefficient magnitude the daemon sends [deg/s per term unit]. A drift term that large
is a fault (a fit gone wrong, a file in rad/s), not a calibration; the virtual unit NAKs beyond it."""

MAX_REPORT_COEFF_DPS = 1000.0
"""A read-back beyond this [deg/s per term unit] is refused as corrupt: no gyro's drift is that large."""


def parse_temp_range(value: Any, where: str) -> tuple[float, float]:
    """``LO,HI`` (text) or [LO, HI] as a temperature range [degC], LO < HI. Raises ConfigError."""
    parts = value.split(",") if isinstance(value, str) else value
    try:
        lo, hi = (float(v) for v in parts)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: {value!r} is not a temperature range; fix: two numbers LO,HI in degC, "
                          "e.g. 21.5,48.0") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ConfigError(f"{where}: {value!r}: LO must be below HI, both finite degC")
    return lo, hi


def check_set(terms: Any, coeffs: Any) -> str | None:
    """Why this set must not be pushed, or None. Checked before anything is stored or sent: term count
    (<= MAX_TERMS), a term set the protocol knows, 3 finite rows of that length, within range."""
    if not isinstance(terms, list | tuple) or not terms or not all(isinstance(t, str) for t in terms):
        return "terms must be a non-empty list of term names"
    if len(terms) > MAX_TERMS:
        return f"{len(terms)} terms; the protocol carries at most {MAX_TERMS}"
    try:
        tid = terms_id(list(terms))
    except Exception as err:
        return f"terms {list(terms)} cannot name a term set ({err})"
    if names_for(tid) is None or len(names_for(tid) or ()) != len(terms):
        return (f"terms {list(terms)} are not a term set this daemon knows: push its estimator.terms or "
                "a set of the protocol's table (docs/protocol.md, section 4)")
    try:
        c = np.asarray(coeffs, dtype=np.float64)
    except (TypeError, ValueError):
        return f"coefficients must be 3 rows of {len(terms)} numbers"
    if c.shape != (3, len(terms)):
        return f"coefficients must be 3 rows of {len(terms)} numbers, got shape {list(c.shape)}"
    if not np.all(np.isfinite(c)):
        return "coefficients hold NaN or Inf"
    worst = float(np.max(np.abs(c)))
    if worst > MAX_PUSH_COEFF_DPS:
        return f"a coefficient of {worst:g} deg/s per term unit exceeds the limit {MAX_PUSH_COEFF_DPS:g}"
    return None


def check_report(msg: CoeffReport) -> str | None:
    """Why a COEFF_REPORT must be refused, or None: non-finite, absurd, or of an unknown shape."""
    rows = msg.coeffs_dps
    if len(rows) != 3 or len({len(r) for r in rows}) != 1:
        return "a report of 3 rows of equal length was expected"
    flat = [c for r in rows for c in r]
    if not all(isinstance(c, int | float) and math.isfinite(c) for c in flat):
        return "it holds NaN or Inf"
    if flat and max(abs(c) for c in flat) > MAX_REPORT_COEFF_DPS:
        return f"a coefficient beyond {MAX_REPORT_COEFF_DPS:g} deg/s per term unit"
    n = len(rows[0])
    if n and len(names_for(msg.terms_id) or ()) != n:
        return f"terms id 0x{msg.terms_id:04x} with {n} terms is not a term set this daemon knows"
    return None


class PushPhase(enum.Enum):
    IDLE = "idle"
    WAIT_ACK = "wait_ack"
    BACKOFF = "backoff"  # a transient failure: waiting before the next write
    WAIT_READBACK = "wait_readback"
    DONE = "done"
    FAILED = "failed"


@dataclass
class PushResult:
    """What a push ended as; stored with the calibration record."""

    status: str  # acked | nak | timeout | link_down | crc_mismatch | readback_mismatch | readback_timeout
    attempts: int
    acked_crc: int | None = None
    readback_ok: bool = False
    reasons: list[str] = field(default_factory=list)
    transient: bool = False  # the unit may accept the same set later (BUSY, silence, link down)
    nak_reason: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"status": self.status, "attempts": self.attempts, "acked_crc": self.acked_crc,
                "readback_ok": self.readback_ok, "reasons": list(self.reasons),
                "transient": self.transient, "nak_reason": self.nak_reason}


FINAL_NAKS = frozenset({int(NakReason.UNKNOWN_TERMS), int(NakReason.OUT_OF_RANGE), int(NakReason.BAD_LENGTH)})
"""NAK reasons that the same set would get again: no retry."""


class PushTransaction:
    """One push of one coefficient set: COEFF_WRITE -> COEFF_ACK(crc) -> COEFF_READ -> COEFF_REPORT."""

    def __init__(
        self, write: CoeffWrite, send: Callable[[Any], None], now: float,
        ack_timeout_s: float = 1.0, retries: int = 3, *, backoff_s: float = 0.5, backoff_max_s: float = 8.0,
        quiet: bool = False,
    ) -> None:
        self.write = write
        # a later round of a version whose first round failed transiently (a unit BUSY for an hour: an
        # autopilot armed, or learning its own calibration): its lines are INFO, the first round's
        # WARNINGs said it already. At 7 WARNING/ERROR lines a round, every 80-300 s, an operator
        # learnt to ignore them (an integrator's audit)
        self._warn = logging.INFO if quiet else logging.WARNING
        self.expected_crc = coeff_set_crc(write.version, write.terms_id, write.coeffs_dps)
        self._send = send
        self.timeout_s = ack_timeout_s
        self.retries = retries
        self.attempts = 0
        self.read_attempts = 0
        self.reasons: list[str] = []
        self.phase = PushPhase.IDLE
        self.result: PushResult | None = None
        self.acked_crc: int | None = None
        self.backoff_s, self.backoff_max_s = backoff_s, backoff_max_s
        self.send_failures = 0
        self._outage_said = False  # the last send failed on a link the session already said is down
        self.link_down = False  # the engine has said the link is lost (session.link_lost): acks cannot come
        self.nak_reason: int | None = None
        self._rng = random.Random(write.version)  # jitter, seeded: the same push retries the same way
        self._deadline = 0.0
        self._attempt(now)

    @property
    def finished(self) -> bool:
        return self.phase in (PushPhase.DONE, PushPhase.FAILED)

    def _safe_send(self, msg: Any) -> bool:
        """Send; a link failure becomes a recorded reason, never an exception (the engine must live)."""
        try:
            # the session's send says False for a link that took nothing (it logs the outage once);
            # read as success, a dead link's push waited out its acks and ended 'timeout' where
            # protocol.md says 'link_down' (an operator's audit)
            if self._send(msg) is False:
                self._outage_said = True
                raise OSError("the link takes no sends")
            self._outage_said = False
        except Exception as err:  # LinkError / OSError: the unit is unplugged or the write failed
            self.send_failures += 1
            reason = f"{type(msg).__name__} not sent: {err}"
            self.reasons.append(reason)
            # a write's failure is logged once, by _retry_or_fail; a read's here
            log.log(logging.DEBUG if isinstance(msg, CoeffWrite) else logging.WARNING,
                    "push v%d: %s", self.write.version, reason)
            return False
        return True

    def _attempt(self, now: float) -> None:
        self.attempts += 1
        self.phase = PushPhase.WAIT_ACK
        self._deadline = now + self.timeout_s
        log.info("push v%d: COEFF_WRITE attempt %d/%d", self.write.version, self.attempts, self.retries)
        if not self._safe_send(self.write):
            # nothing left the host: no ack to wait for; back off, then try again (or give up). A link the
            # session already said is down (its send's False, one WARNING per outage) is not said again:
            # one cable pull mid-push gave 5 WARNINGs, two of them this one fact (an integrator's fault
            # campaign, F3)
            self._retry_or_fail(now, "timeout", f"attempt {self.attempts}: the write could not be sent",
                                level=logging.INFO if self._outage_said else None)

    def _backoff(self) -> float:
        """Delay before the next write [s]: doubling per attempt, capped, +-25 % jitter."""
        base = min(self.backoff_s * 2.0 ** max(0, self.attempts - 1), self.backoff_max_s)
        return base * self._rng.uniform(0.75, 1.25)

    def _read(self, now: float) -> None:
        self.read_attempts += 1
        self.phase = PushPhase.WAIT_READBACK
        self._deadline = now + self.timeout_s
        self._safe_send(CoeffRead())

    def _retry_or_fail(self, now: float, status: str, reason: str, *, final: bool = False,
                       level: int | None = None) -> None:
        self.reasons.append(reason)
        log.log(self._warn if level is None else level, "push v%d: %s", self.write.version, reason)
        if self.attempts < self.retries and not final:
            self.phase = PushPhase.BACKOFF
            self._deadline = now + self._backoff()
        else:
            if status == "timeout" and self.send_failures >= self.attempts:
                status = "link_down"  # no write ever left the host
            self._finish(status, ok=False, transient=not final)

    def _finish(self, status: str, ok: bool, readback_ok: bool = False, transient: bool = False) -> None:
        self.phase = PushPhase.DONE if ok else PushPhase.FAILED
        self.result = PushResult(status, self.attempts, self.acked_crc, readback_ok, list(self.reasons),
                                 transient=transient and not ok,
                                 # the NAK that ended it; an earlier attempt's stays in reasons
                                 nak_reason=self.nak_reason if status == "nak" else None)
        # a transient failure is tried again by the session (WARNING); a final one is not (ERROR)
        level = logging.INFO if ok else self._warn if self.result.transient else logging.ERROR
        log.log(level, "push v%d ended: %s after %d attempt(s)", self.write.version, status, self.attempts)

    def on_message(self, msg: Any, now: float) -> bool:
        """Feed a message from the unit; returns True if the push consumed it."""
        if self.finished:
            return False
        if isinstance(msg, CoeffAck) and self.phase is PushPhase.BACKOFF \
                and msg.version == self.write.version and msg.crc == self.expected_crc:
            # the ack of an attempt whose timeout passed, before the next attempt: the unit holds the
            # set (the read-back checks it). Ignored, a unit acking in 0.8 s after a reload cut
            # ack_timeout_s to 0.5 had v9 written 5 times, 5 acks came, and the push was recorded
            # 'timeout' (an integrator's campaign, rc33 G7; protocol.md: a later answer is not lost)
            log.info("push v%d: the ack of attempt %d came after its %.1f s timeout; reading the set back",
                     self.write.version, self.attempts, self.timeout_s)
            self.acked_crc = msg.crc
            self._read(now)
            return True
        if isinstance(msg, CoeffAck) and self.phase is PushPhase.WAIT_ACK:
            if msg.version != self.write.version:
                return False
            if msg.crc != self.expected_crc:
                self._retry_or_fail(
                    now, "crc_mismatch",
                    f"ack CRC 0x{msg.crc:08x} differs from the set's 0x{self.expected_crc:08x}",
                )
                return True
            self.acked_crc = msg.crc
            self._read(now)
            return True
        if isinstance(msg, CoeffNak) and self.phase is PushPhase.WAIT_ACK:
            if msg.version != self.write.version:
                return False
            self.nak_reason = int(msg.reason)
            self._retry_or_fail(now, "nak", f"unit answered NAK (reason {_nak_name(msg.reason)})",
                                final=int(msg.reason) in FINAL_NAKS)
            return True
        if isinstance(msg, CoeffReport) and self.phase is PushPhase.WAIT_READBACK:
            try:
                crc = coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps)
            except ProtocolError as err:  # NaN/Inf or a malformed set under a valid frame CRC
                self.reasons.append(f"read-back v{msg.version} refused: {err}")
                log.log(self._warn, "push v%d: read-back refused (%s); reading again", self.write.version,
                        err)
                self._deadline = min(self._deadline, now + self.timeout_s / 2)
                return True
            if crc == self.expected_crc:
                self._finish("acked", ok=True, readback_ok=True)
            else:
                self.reasons.append(f"read-back v{msg.version} CRC 0x{crc:08x} differs from the set sent")
                self._finish("readback_mismatch", ok=False)
            return True
        return False

    def tick(self, now: float) -> None:
        """Advance timeouts; call often (every engine loop)."""
        if self.finished or now < self._deadline:
            return
        if self.phase is PushPhase.BACKOFF:
            self._attempt(now)
        elif self.phase is PushPhase.WAIT_ACK:
            # with the link said lost, the missing ack is that loss's consequence, not a second fault
            self._retry_or_fail(now, "timeout", f"no ack within {self.timeout_s:.1f} s",
                                level=logging.INFO if self.link_down else None)
        elif self.phase is PushPhase.WAIT_READBACK:
            if self.read_attempts < self.retries:
                self._read(now)
            else:
                self.reasons.append("no COEFF_REPORT after the ack")
                self._finish("readback_timeout", ok=False, transient=True)


def _nak_name(reason: int) -> str:
    try:
        return f"{NakReason(int(reason)).name} ({int(reason)})"
    except ValueError:
        return str(reason)
