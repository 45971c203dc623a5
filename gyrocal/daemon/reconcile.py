"""Reconciliation: the unit's read-back is the truth, and the store is brought into line with it.

Why: a push can be cut at any moment (the ack lost on the wire, the unit power-cycled right after
its ack, the daemon killed mid-push, the cable pulled). The unit applies a set whole or not at all,
so after any of these the unit holds either the old set or the new one, and only its COEFF_REPORT
says which. The store, written by the daemon, may say 'pending' or 'timeout' for a set the unit in
fact holds. Left alone, warm start and rollback would then skip the very set the unit uses.

Rules (applied at every read-back: the session's first COEFF_READ after a HELLO or a reconnect, and
every push's read-back; and at daemon start for the store alone):

- a report whose CRC matches a stored version of this unit that is not already marked applied
  ('pending', 'timeout', 'nak', 'link_down', 'abandoned', ...) marks that version
  ``applied_ack_lost``: the unit verifiably holds it, although the push never saw its ack. The old
  status and the time are kept in ``push.history``, so nothing that happened is erased. A push that
  saw its ack (its ``acked_crc`` the report's) and ended ``readback_timeout`` becomes ``acked``;
- a report whose version is stored but whose CRC differs is a disagreement: reported in status and
  logged once, never "fixed" by rewriting the record (the unit may hold a set another tool wrote);
- on a unit that measures its own bias at boot (``own_boot_bias``: ArduPilot's gyro calibration),
  a report of a stored version whose temperature terms are the record's and whose constant differs
  agrees: the unit holds that set with the bias of this boot, which is what it is built to do.
  Without this, every ArduPilot reboot was reported as a CRC disagreement (an integrator's audit);
- a report of a version the store does not know (another host, a factory set) is reported as such;
- at daemon start, every 'pending' record is closed as ``abandoned`` (reason: the daemon stopped
  before its push finished). If the unit turns out to hold it, the first read-back makes it
  ``applied_ack_lost``.

Warm start and rollback use :data:`APPLIED_STATUSES` ('acked' and 'applied_ack_lost'): sets the unit
verifiably held.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from gyrocal.daemon.store import APPLIED_STATUSES, CalibrationRecord, CalibrationStore, utc_now
from gyrocal.errors import ProtocolError
from gyrocal.protocol.messages import coeff_set_crc
from gyrocal.protocol.termsets import names_for, terms_id

log = logging.getLogger("gyrocal.reconcile")


def record_crc(rec: CalibrationRecord) -> int | None:
    """The wire CRC of a stored set (what the unit's ack and read-back carry), None if not encodable."""
    try:
        return coeff_set_crc(rec.version, terms_id(rec.terms), rec.coefficients_dps)
    except (ProtocolError, ValueError, KeyError):
        return None


@dataclass
class Agreement:
    """The unit's set against the store's view of it, for status."""

    unit_version: int
    unit_crc: int | None
    store_status: str | None  # push status of that version in the store, None if unknown to it
    agree: bool
    note: str
    own_bias_dph: list[float] | None = None  # the unit's boot-measured constant minus the stored one
    # why the store could not take the settled status (to be tried again), or None
    store_failed: str | None = None

    def as_dict(self) -> dict[str, Any]:
        out = {"agree": self.agree, "note": self.note, "unit_version": self.unit_version,
               "unit_crc": None if self.unit_crc is None else f"0x{self.unit_crc:08x}",
               "store_status": self.store_status}
        if self.own_bias_dph is not None:
            out["own_bias_dph"] = self.own_bias_dph
        return out


def own_bias_of(rec: CalibrationRecord, report: Any) -> np.ndarray | None:
    """[deg/s] (3,) The report's constant minus the record's, when every other term's coefficients
    are the record's (to float32 rounding, as an autopilot holds them) and any term the record lacks
    is 0 in the report (an autopilot reports its whole cubic); None otherwise."""
    try:
        names = list(rec.terms)
        got_names = names_for(int(report.terms_id))
        got = np.asarray(report.coeffs_dps, dtype=np.float64)
        want = np.asarray(rec.coefficients_dps, dtype=np.float64)
    except (ProtocolError, ValueError, KeyError, TypeError):
        return None
    if "1" not in names or got_names is None or "1" not in got_names or not set(names) <= set(got_names) \
            or got.shape != (3, len(got_names)) or want.shape != (3, len(names)):
        return None
    for j, name in enumerate(got_names):
        if name == "1":
            continue
        ref = want[:, names.index(name)] if name in names else np.zeros(3)
        if not np.allclose(got[:, j], ref, rtol=1e-5, atol=1e-9):
            return None
    return got[:, got_names.index("1")] - want[:, names.index("1")]


def reconcile(store: CalibrationStore, serial: int, version: int, crc: int | None,
              report: Any = None, own_boot_bias: bool = False) -> Agreement:
    """Bring the store into line with a read-back of ``version`` with wire ``crc`` (see module doc).

    Raises nothing for a store that cannot be written: the caller gets the agreement with a note and
    ``store_failed``, and tries again (``Session._reconcile_again``).
    """
    if version == 0:
        coeffs = getattr(report, "coeffs_dps", None)
        if coeffs is not None and np.any(np.asarray(coeffs, dtype=np.float64) != 0.0):
            # an autopilot reports what it subtracts under version 0 when the set is not one of ours
            # (its own gyro calibration, another tool's set, a board remounted since our push): "no
            # set" was said of a remounted board that held one (an integrator's audit)
            return Agreement(0, crc, None, True, "the unit holds a set gyrocal did not write (version 0 "
                             "with non-zero coefficients: its own or another tool's calibration, or a "
                             "set of ours whose frame or parameters changed since)")
        return Agreement(0, crc, None, True, "the unit holds no set (version 0)")
    rec = store.get(serial, version)
    if rec is None:
        return Agreement(version, crc, None, False,
                         f"the unit holds v{version}, which this store does not know "
                         "(written by another host?)")
    status = str(rec.push.get("status"))
    bias = None
    if crc is not None and record_crc(rec) != crc and own_boot_bias and report is not None:
        bias = own_bias_of(rec, report)
    own = None if bias is None else [round(float(b) * 3600, 3) for b in bias]
    boot_note = "" if own is None else (
        ", with the constant its own gyro calibration measured at boot ("
        + "/".join(f"{b:.3g}" for b in own) + " deg/h from the stored one)")
    if bias is None and (crc is None or record_crc(rec) != crc):
        return Agreement(version, crc, status, False,
                         f"the unit holds a v{version} whose CRC differs from the stored v{version}")
    if status in APPLIED_STATUSES:
        return Agreement(version, crc, status, True,
                         f"the unit holds v{version}, as the store says{boot_note}", own)
    history = list(rec.push.get("history") or [])
    history.append({"status": status, "reasons": rec.push.get("reasons"), "until_utc": utc_now()})
    # a push whose ack came and whose read-back did not (the unit switched off right after its ack):
    # 'acked', read back now. Called 'applied (ack lost)' with an ERROR, its record's own history said
    # the ack had come (a fleet engineer's power cuts)
    acked = status == "readback_timeout" and crc is not None and rec.push.get("acked_crc") == crc
    new = "acked" if acked else "applied_ack_lost"
    try:
        store.update_push(serial, version, {"status": new, "acked_crc": crc,
                                            "readback_ok": True, "history": history,
                                            "reconciled_utc": utc_now()})
    except Exception as err:  # a full disk: say so; the caller tries again (store_failed)
        return Agreement(version, crc, status, False,
                         f"the unit holds v{version} (stored as {status!r}); store not updated: {err}",
                         store_failed=str(err))
    if acked:
        log.info("unit %d holds v%d, acked before its read-back was lost: read back now, recorded as acked",
                 serial, version)
        return Agreement(version, crc, "acked", True,
                         f"the unit holds v{version}; its ack had come, its read-back now{boot_note}", own)
    log.warning("unit %d holds v%d although its push ended %r: recorded as applied (ack lost)",
                serial, version, status)
    return Agreement(version, crc, "applied_ack_lost", True,
                     f"the unit holds v{version}; its push had ended {status!r}: now applied (ack lost)"
                     f"{boot_note}", own)


def close_abandoned(store: CalibrationStore) -> int:
    """At daemon start: mark every 'pending' record 'abandoned' with a reason; returns how many."""
    closed = 0
    for serial in store.units():
        for rec in store.history(serial):
            if rec.push.get("status") != "pending":
                continue
            try:
                store.update_push(serial, rec.version, {
                    "status": "abandoned", "time": utc_now(),
                    "reasons": [*(rec.push.get("reasons") or []),
                                "the daemon stopped before this push finished; the unit's read-back decides "
                                "whether it was applied"]})
                closed += 1
            except Exception as err:  # a read-only store: it stays 'pending', which says as much
                log.warning("calibration store: cannot close pending v%d of unit %d: %s",
                            rec.version, serial, err)
    if closed:
        log.info("calibration store: %d push(es) left pending by an earlier run closed as abandoned", closed)
    return closed
