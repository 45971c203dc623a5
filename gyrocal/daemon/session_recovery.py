"""The session's fault paths: sends that fail, reading the unit's set, the store that fails.

Split from session.py (the state machine) so each stays small; the rules themselves are written
down once, in session.py's docstring ("Recovery rules"). A mixin of ``Session``: it uses the
session's ``cfg``, ``hello``, ``store``, ``send``, ``push`` and its bookkeeping fields.
"""

from __future__ import annotations

import logging
from typing import Any

from gyrocal.daemon.reconcile import Agreement, reconcile
from gyrocal.daemon.store import APPLIED_STATUSES, utc_now
from gyrocal.protocol.messages import CoeffRead, CoeffReport, coeff_set_crc

log = logging.getLogger("gyrocal.session")


class RecoveryMixin:
    """Send, read-back, reconciliation and store-retry methods of ``Session``."""

    READ_BACKOFF_MAX_S = 30.0
    """Longest wait between two unanswered COEFF_READs [s]."""
    READ_WARN_AFTER = 3
    """Unanswered COEFF_READs before the one WARNING."""
    RETRY_BACKOFF_S = 5.0
    """First wait before a transiently failed push is sent again (same version) [s]; doubles."""
    RETRY_BACKOFF_MAX_S = 300.0
    """Longest wait between two rounds of the same push [s]."""
    RANGE_NAKS_MAX = 3
    """New sets NAKed OUT_OF_RANGE in a row after which a session pushes no more (session.range_hold)."""
    STORE_RETRY_S = 5.0
    """Wait before writing to a store that failed again [s]."""

    cfg: Any
    hello: Any
    store: Any
    send: Any
    push: Any
    applied: Any
    _switch: Any
    last_push: dict[str, Any]
    agreement: dict[str, Any]
    unrecorded: list[tuple[int, dict[str, Any]]]
    store_error: str | None
    send_failures: int
    _link_warned: bool
    _read_asks: int
    _read_deadline: float
    _store_retry_at: float
    _retry: Any
    _push_due: Any = None
    _disagreement_said: str | None = None
    _reconcile_again: dict[int, Any] | None = None  # version -> its read-back the store could not settle

    def _forget_set(self) -> None: ...  # Session's: the unit's set is unknown until read again

    def _being_pushed(self, msg: CoeffReport) -> bool: ...  # Session's: the set of the push under way

    def _send(self, msg: Any) -> bool:
        """Send to the unit; a link failure is counted and logged once per outage, never raised."""
        try:
            self.send(msg)
        except Exception as err:  # LinkError / OSError: unplugged, or a write that failed
            self.send_failures += 1
            if not self._link_warned:
                log.warning("unit %s: %s not sent (%s); the session waits for the link",
                            self.hello.serial, type(msg).__name__, err)
                self._link_warned = True
            return False
        self._link_warned = False
        return True

    def close(self, reason: str, now: float) -> None:
        """The session ends (a new switch-on, a recalibration): a push still under way is recorded as
        'abandoned' with the reason; the next read-back decides whether the unit applied it."""
        due = self._push_due
        if due is not None:  # recorded by a slow store, never sent: the unit keeps its set
            self._push_due = None
            self.last_push = {"version": due["version"], "status": "abandoned", "utc": utc_now(),
                              "reasons": [f"not sent: {reason} before the slow store's write was caught up"]}
            log.info("unit %s: v%d not pushed: %s", self.hello.serial, due["version"], reason)
            self._store_push(due["version"], dict(self.last_push), now)
        if self.push is not None:
            push, self.push = self.push, None
            version = push.write.version
            if push.acked_crc is not None:
                # acked, its read-back cut short (a unit switched off right after its ACK): the record
                # keeps the ack, and the next read-back of the set makes it 'acked'. Recorded as
                # 'abandoned', it became 'applied (ack lost)' with two WARNINGs (an integrator's check)
                self.last_push = {"version": version, "status": "readback_timeout", "utc": utc_now(),
                                  "attempts": push.attempts, "acked_crc": push.acked_crc,
                                  "reasons": [*push.reasons, f"read-back cut short: {reason}"]}
                log.info("unit %s: v%d was acked; its read-back was cut short (%s): the next one decides",
                         self.hello.serial, version, reason)
            else:
                self.last_push = {"version": version, "status": "abandoned", "utc": utc_now(),
                                  "attempts": push.attempts,
                                  "reasons": [f"push cut short: {reason}; the unit's read-back decides"]}
                log.warning("unit %s: push of v%d abandoned: %s", self.hello.serial, version, reason)
            self._store_push(version, dict(self.last_push), now)
        self._retry = None

    def link_lost(self) -> None:
        """The engine has said the link is lost (its WARNING): what the session sends meanwhile fails
        for that reason, and a push's missing ack is its consequence, neither said again at WARNING.
        One cable pull mid-push gave the loss, 'no ack within 1.0 s' and 'CoeffWrite not sent' as three
        WARNINGs (an integrator's fault campaign, F3)."""
        self._link_warned = True
        if self.push is not None:
            self.push.link_down = True

    def relink(self, now: float) -> None:
        """The link came back: the unit may have changed its set meanwhile; read it again."""
        self._read_asks = 0
        if self.push is not None:
            self.push.link_down = False
        else:
            self._forget_set()
        self.request_read(now)

    def request_read(self, now: float) -> None:
        """Ask for the unit's set (COEFF_READ), with a back-off while it does not answer. A read the
        link did not take is not the unit's silence: it is asked again after ``push.ack_timeout_s``.
        With the back-off doubling through a 10 s CAN bus outage, the set was read back 7 s after the
        samples returned, and none of them was learnt meanwhile (an integrator's campaign, rc33 G4)."""
        sent = self._send(CoeffRead())
        if sent:  # an ask the link did not take is not one the unit left unanswered
            self._read_asks += 1
        delay = min(self.cfg.push["ack_timeout_s"] * 2.0 ** max(0, self._read_asks - 1),
                    self.READ_BACKOFF_MAX_S) if sent else self.cfg.push["ack_timeout_s"]
        self._read_deadline = now + max(delay, 0.05)

    def _reconcile(self, msg: CoeffReport) -> None:
        try:
            crc = coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps) if msg.version else None
            held = self._held_in_memory(msg.version, crc)
            if held is None and self._being_pushed(msg):
                # its record is 'pending' because its push is under way, not because it ended so:
                # "holds v8 although its push ended 'pending': recorded as applied (ack lost)" was
                # said mid-push, and the push's own ack then overwrote that record (F3)
                held = Agreement(msg.version, crc, "pending", True,
                                 f"the unit holds v{msg.version}, the set being pushed (its ack not heard "
                                 "yet)")
            agreement = held or reconcile(self.store, self.hello.serial, msg.version, crc, msg,
                                          own_boot_bias=self.caps.own_boot_bias)
            self.agreement = agreement.as_dict()
            if agreement.store_failed:
                # a read-only store at the read-back: the record stayed 'pending' for good, status said
                # the unit disagreed with it after the store was writable again, and the next start
                # closed the set the unit had acked and held as 'abandoned' (an integrator's fault
                # campaign, F1). Settled again every STORE_RETRY_S (_settle_again)
                self._reconcile_again = {**(self._reconcile_again or {}), msg.version: msg}
                # status's faults.store said "ok" for 15 s of a daemon restarted on a full disk, while
                # the journal said ENOSPC and the acked set stayed 'pending' (an integrator's campaign,
                # G5); _settle_again says "ok" again once it is settled
                if self.store_error is None:
                    self.store_error = agreement.store_failed
        except Exception as err:  # the store is advisory here: learning goes on
            self.agreement = {"unit_version": msg.version, "agree": False, "note": f"not reconciled: {err}"}
        lp = self.last_push
        settled = self.agreement.get("store_status")
        if settled in APPLIED_STATUSES and lp.get("version") == msg.version \
                and lp.get("status") not in APPLIED_STATUSES:
            # the store's record became 'applied (ack lost)' (or 'acked': its read-back was lost);
            # status's last_push kept saying 'timeout', readback_ok false, for a set the unit holds (a
            # serial integrator's unplug mid-push)
            self.last_push = {**lp, "status": settled, "readback_ok": True,
                              "acked_crc": crc,
                              "reconciled_utc": utc_now()}
        note = self.agreement.get("note")
        if not self.agreement.get("agree") and note != self._disagreement_said:
            # one line per new disagreement, not per read-back: status keeps showing it (unit_set)
            self._disagreement_said = note
            known = self.agreement.get("store_status") is not None
            log.log(logging.WARNING if known else logging.INFO,
                    "unit %s: %s; the store keeps its record, and learning uses the unit's set",
                    self.hello.serial, note)
        elif self.agreement.get("agree"):
            if self.agreement.get("own_bias_dph") is not None and self._disagreement_said != note:
                log.info("unit %s: %s", self.hello.serial, note)  # once per switch-on: its boot's bias
                self._disagreement_said = note
            elif self.agreement.get("own_bias_dph") is None:
                self._disagreement_said = None

    def _held_in_memory(self, version: int, crc: int | None) -> Agreement | None:
        """The read-back against this session's own push result for ``version`` when the store could not
        take it yet (``unrecorded``): the store's 'pending' is not the truth then, and reconciling
        against it logged "the unit holds v44 although its push ended 'pending': recorded as applied
        (ack lost)" for a push whose ack had come, and status kept saying so after the store was freed
        (an operator's soak). None when no such result is held."""
        for v, push in reversed(self.unrecorded):
            if v == version and push.get("status") in APPLIED_STATUSES and push.get("acked_crc") == crc:
                return Agreement(version, crc, str(push["status"]), True,
                                 f"the unit holds v{version}, as its push result says (kept in memory until "
                                 "the store takes it)")
        return None

    def _store_push(self, version: int, push: dict[str, Any], now: float) -> None:
        """Record a push result; a store that cannot take it keeps it in memory for later."""
        try:
            self.store.update_push(self.hello.serial, version, push)
        except KeyError as err:  # no such record (a push of a set that was never stored): nothing to update
            log.warning("store: push result of v%d not recorded: %s", version, err)
        except Exception as err:  # the store must never take the session down with it
            if self.store_error is None:
                log.error("store unavailable: cannot record the push result of v%d (%s); kept in memory, "
                          "retried every %g s", version, err, self.STORE_RETRY_S)
            self.store_error = str(err)
            self.unrecorded.append((version, push))
            self._store_retry_at = now + self.STORE_RETRY_S

    def _settle_again(self, now: float) -> None:
        """Settle again the records of read-backs the store could not take (``_reconcile_again``),
        every STORE_RETRY_S until it does. A set the unit has replaced since is settled too (it held
        it); status's agreement changes only for the set it holds now."""
        waiting, self._reconcile_again = self._reconcile_again or {}, None
        for version, msg in waiting.items():
            crc = coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps)
            try:
                agreement = reconcile(self.store, self.hello.serial, version, crc, msg,
                                      own_boot_bias=self.caps.own_boot_bias)
            except Exception:  # the store is advisory here, as in _reconcile
                agreement = None
            if agreement is None or agreement.store_failed:
                self._reconcile_again = {**(self._reconcile_again or {}), version: msg}
                continue
            if self.agreement.get("unit_version") == version:
                self.agreement = agreement.as_dict()
            log.info("store available again: the unit's v%d settled as %s", version, agreement.store_status)
        if self._reconcile_again:
            self._store_retry_at = now + self.STORE_RETRY_S
        elif self.store_error is not None and not self.unrecorded:
            self.store_error = None

    def _flush_unrecorded(self, now: float) -> None:
        pending, self.unrecorded = self.unrecorded, []
        for version, push in pending:
            self._store_push(version, push, now)
        if not self.unrecorded:
            self.store_error = None
            log.info("store available again: %d push result(s) recorded", len(pending))
            if str(self.agreement.get("note", "")).endswith("until the store takes it)"):
                held = self.agreement.get("unit_version")
                self.agreement = {**self.agreement, "note": f"the unit holds v{held}, as the store says"}
