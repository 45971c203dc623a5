"""The replayed unit: what a recording can answer, and how its output changes after a push.

The recording fixes what the unit *measured*; it cannot say what the unit would have sent had it
received our COEFF_WRITE. We answer as a unit of the protocol would (docs/protocol.md):

- HELLO_REQUEST: the recording's HELLO (the current switch-on's, else the first one recorded; a
  recording with none, started after the switch-on, gets an anonymous HELLO: serial 0, boot 0);
- COEFF_READ: COEFF_REPORT of the set the unit holds: the recording's (its first COEFF_REPORT, or
  an empty set when the recording never shows one: a log of uncompensated output), or ours once we
  pushed one;
- COEFF_WRITE: checked as the unit checks it (known terms_id, n_terms, finite values), then applied
  and acked with the CRC of the set: the push is *recorded* (``pushes``), nothing is sent anywhere.

A unit outputs raw - C_applied . phi. After our push the recorded output (compensated with the
recorded set C_rec) is re-compensated: out = out_rec + C_rec . phi - C_ours . phi, with phi from the
same inputs the daemon uses (measured accel, temperature, t_on = the unit time sent, dtemp by the
protocol's rule, section 6), so the daemon's monitoring sees what the pushed set would have done to
the recorded data. The recording's own COEFF_ACK,
COEFF_NAK and COEFF_REPORT answered another host: they update C_rec, never reach the daemon.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from gyrocal.daemon.session import AppliedSet
from gyrocal.model.terms import TermSpec
from gyrocal.protocol.messages import (
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffWrite,
    Hello,
    HelloRequest,
    NakReason,
    coeff_set_crc,
)
from gyrocal.protocol.termsets import TempRate, names_for

EMPTY_SET = CoeffReport(version=0, terms_id=0, coeffs_dps=((), (), ()))
"""What a unit that holds no calibration reports."""


class ReplayUnit:
    """Answers host messages from a recording's state; re-compensates output after a push."""

    def __init__(self, first_hello: Hello | None = None, first_report: CoeffReport | None = None) -> None:
        self.hello = first_hello
        self.recorded = AppliedSet.from_report(first_report or EMPTY_SET)
        self._recorded_msg = first_report or EMPTY_SET
        self.ours: AppliedSet | None = None  # None: nothing pushed in this replay, the recorded set holds
        self._ours_msg: CoeffReport | None = None
        self.pushes: list[dict[str, Any]] = []
        self.synthesized_hello = False
        self.unit_time_s = 0.0
        self._sampled = False  # samples came in this switch-on (before any HELLO: recorded after it)
        self._trate = TempRate()  # dtemp by the protocol's rule (section 6), from the recording's start
        self._spec_key: tuple[tuple[str, ...], tuple[str, ...]] | None = None
        self._spec_ours: TermSpec | None = None
        self._spec_rec: TermSpec | None = None

    # -- the recording -------------------------------------------------------------------------
    def on_recorded(self, msg: Any) -> bool:
        """A recorded unit message; True when it goes on to the daemon (a HELLO only)."""
        if isinstance(msg, Hello):
            h = self.hello
            if h is None or (msg.serial, msg.boot_count) != (h.serial, h.boot_count):
                self._sampled = False
                self._trate = TempRate()
            self.hello = msg
            return True
        if isinstance(msg, CoeffReport):
            self.recorded, self._recorded_msg = AppliedSet.from_report(msg), msg
        return False

    # -- the host ------------------------------------------------------------------------------
    def answer(self, msg: Any) -> list[Any]:
        """What the unit sends back to a host message (possibly nothing)."""
        if isinstance(msg, HelloRequest):
            if self.hello is None and self._sampled:
                # samples came first: recorded after the switch-on, no HELLO to come. An anonymous unit
                self.hello = Hello(0, "0.0.0", 0)
                self.synthesized_hello = True
            return [self.hello] if self.hello is not None else []
        if isinstance(msg, CoeffRead):
            return [self._ours_msg if self._ours_msg is not None else self._recorded_msg]
        if isinstance(msg, CoeffWrite):
            return [self._write(msg)]
        return []

    def _write(self, msg: CoeffWrite) -> CoeffAck | CoeffNak:
        names = names_for(msg.terms_id)
        rows = np.asarray(msg.coeffs_dps, dtype=np.float64)
        crc = coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps)
        entry = {"version": msg.version, "terms": list(names or ()), "terms_id": msg.terms_id,
                 "coefficients_dps": rows.tolist(), "unit_time_s": round(self.unit_time_s, 6),
                 "session_boot": None if self.hello is None else self.hello.boot_count}
        reason = None
        if names is None:
            reason = NakReason.UNKNOWN_TERMS
        elif rows.shape != (3, len(names)):
            reason = NakReason.BAD_LENGTH
        elif not all(math.isfinite(v) for v in rows.ravel()):
            reason = NakReason.OUT_OF_RANGE
        if reason is not None:
            self.pushes.append({**entry, "status": "refused", "reason": reason.name})
            return CoeffNak(msg.version, crc, int(reason))
        self.ours = AppliedSet(msg.version, msg.terms_id, tuple(names), rows)
        self._ours_msg = CoeffReport(msg.version, msg.terms_id, msg.coeffs_dps)
        self.pushes.append({**entry, "status": "recorded"})
        return CoeffAck(msg.version, crc)

    # -- the output ----------------------------------------------------------------------------
    def output(self, block: np.ndarray) -> np.ndarray:
        """The block as this unit would send it: re-compensated once a pushed set replaced the recorded."""
        if block.size == 0:
            return block
        self._sampled = True
        self.unit_time_s = float(block["t"][-1])
        dtemp = self._trate.update(block["t"], block["temp"])  # followed whether or not a set uses it
        if self.ours is None:  # the recorded output stands
            return block
        cols = {c: block[c] for c in ("t", "ax", "ay", "az", "temp")}
        cols["t_on"] = block["t"]  # the unit time it sends is since switch-on (protocol.md, section 6)
        cols["dtemp"] = dtemp
        delta = self._delta(cols)
        out = block.copy()
        out["wx"] += delta[:, 0]
        out["wy"] += delta[:, 1]
        out["wz"] += delta[:, 2]
        return out

    def _specs(self) -> tuple[TermSpec, TermSpec | None]:
        """The term specs of our set and (when its terms differ) the recorded set, parsed once."""
        rec, ours = self.recorded, self.ours
        assert ours is not None
        key = (rec.names, ours.names)
        if self._spec_key != key:
            self._spec_key = key
            self._spec_ours = TermSpec.parse(ours.names)
            self._spec_rec = TermSpec.parse(rec.names) if rec.names and rec.names != ours.names else None
        assert self._spec_ours is not None
        return self._spec_ours, self._spec_rec

    def _delta(self, cols: dict[str, np.ndarray]) -> np.ndarray:
        """C_rec . phi - C_ours . phi, (N, 3) [deg/s]: one design matrix when both sets share terms."""
        rec, ours = self.recorded, self.ours
        assert ours is not None
        self._specs()
        phi = self._spec_ours.design(cols)
        if rec.names == ours.names:
            return phi @ (rec.coeffs_dps - ours.coeffs_dps).T
        comp_rec = self._spec_rec.design(cols) @ rec.coeffs_dps.T if self._spec_rec is not None \
            and np.any(rec.coeffs_dps) else 0.0
        return comp_rec - phi @ ours.coeffs_dps.T
