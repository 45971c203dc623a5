"""The coefficient push: write, wait for a matching ack, read back, with retries and timeouts.

Why a separate little state machine: the push is the one moment the daemon changes the unit, and
its failure modes (NAK, silence, an ack whose CRC does not match, a read-back that differs) must each
end in a recorded outcome, never in a half-known unit. The unit applies a set atomically (the
protocol's CRC-checked commit), so a failed push leaves the unit with its old set; after any
failure we read back what the unit holds rather than assume it.

Pure logic: no threads and no I/O. ``send`` is a callable the engine gives; time comes in as
``now`` (monotonic s), so tests drive it deterministically.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from gyrocal.protocol.messages import (
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffWrite,
    coeff_set_crc,
)

log = logging.getLogger("gyrocal.push")


class PushPhase(enum.Enum):
    IDLE = "idle"
    WAIT_ACK = "wait_ack"
    WAIT_READBACK = "wait_readback"
    DONE = "done"
    FAILED = "failed"


@dataclass
class PushResult:
    """What a push ended as; stored with the calibration record."""

    status: str  # acked | nak | timeout | crc_mismatch | readback_mismatch | readback_timeout
    attempts: int
    acked_crc: int | None = None
    readback_ok: bool = False
    reasons: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"status": self.status, "attempts": self.attempts, "acked_crc": self.acked_crc,
                "readback_ok": self.readback_ok, "reasons": list(self.reasons)}


class PushTransaction:
    """One push of one coefficient set: COEFF_WRITE -> COEFF_ACK(crc) -> COEFF_READ -> COEFF_REPORT."""

    def __init__(
        self, write: CoeffWrite, send: Callable[[Any], None], now: float,
        ack_timeout_s: float = 1.0, retries: int = 3,
    ) -> None:
        self.write = write
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
        self._deadline = 0.0
        self._attempt(now)

    @property
    def finished(self) -> bool:
        return self.phase in (PushPhase.DONE, PushPhase.FAILED)

    def _attempt(self, now: float) -> None:
        self.attempts += 1
        self.phase = PushPhase.WAIT_ACK
        self._deadline = now + self.timeout_s
        log.info("push v%d: COEFF_WRITE attempt %d/%d", self.write.version, self.attempts, self.retries)
        self._send(self.write)

    def _read(self, now: float) -> None:
        self.read_attempts += 1
        self.phase = PushPhase.WAIT_READBACK
        self._deadline = now + self.timeout_s
        self._send(CoeffRead())

    def _retry_or_fail(self, now: float, status: str, reason: str) -> None:
        self.reasons.append(reason)
        log.warning("push v%d: %s", self.write.version, reason)
        if self.attempts < self.retries:
            self._attempt(now)
        else:
            self._finish(status, ok=False)

    def _finish(self, status: str, ok: bool, readback_ok: bool = False) -> None:
        self.phase = PushPhase.DONE if ok else PushPhase.FAILED
        self.result = PushResult(status, self.attempts, self.acked_crc, readback_ok, list(self.reasons))
        level = logging.INFO if ok else logging.ERROR
        log.log(level, "push v%d ended: %s after %d attempt(s)", self.write.version, status, self.attempts)

    def on_message(self, msg: Any, now: float) -> bool:
        """Feed a message from the unit; returns True if the push consumed it."""
        if self.finished:
            return False
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
            self._retry_or_fail(now, "nak", f"unit answered NAK (reason {msg.reason})")
            return True
        if isinstance(msg, CoeffReport) and self.phase is PushPhase.WAIT_READBACK:
            crc = coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps)
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
        if self.phase is PushPhase.WAIT_ACK:
            self._retry_or_fail(now, "timeout", f"no ack within {self.timeout_s:.1f} s")
        elif self.phase is PushPhase.WAIT_READBACK:
            if self.read_attempts < self.retries:
                self._read(now)
            else:
                self.reasons.append("no COEFF_REPORT after the ack")
                self._finish("readback_timeout", ok=False)
