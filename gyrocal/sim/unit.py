"""The virtual strapdown unit: the firmware's logic, without any transport.

State, as a real unit keeps it:

- identity: serial number, firmware version;
- flash: the boot counter and the applied coefficient set (version, terms id, coefficients),
  kept across power cycles;
- RAM: the current switch-on session (a ``SessionStream`` with this boot's bias), the sample counter.

The unit outputs the *compensated* rate: raw gyro minus the applied set's compensation, evaluated
per sample from the measured accelerometer [g], the sensor temperature [degC], its rate [degC/s]
and the time since switch-on [s] (the last two from the unit's own thermal state and clock).

``handle`` answers the host: HELLO_REQUEST with this boot's HELLO; COEFF_WRITE is validated and
applied atomically, then acked with the CRC of the set as applied (``coeff_set_crc``), or NAKed
with a reason; COEFF_READ returns a report. Fault injection (``Faults``) lets daemon tests exercise
NAKs, lost acks and a silent switch-on.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from gyrocal.errors import ProtocolError
from gyrocal.model.prep import block_terms
from gyrocal.model.terms import TermSpec
from gyrocal.protocol import termsets
from gyrocal.protocol.messages import (
    SEQ_MODULO,
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffTransferFailed,
    CoeffWrite,
    Hello,
    HelloRequest,
    NakReason,
    Sample,
    coeff_set_crc,
)
from gyrocal.sim.schedule import Schedule
from gyrocal.sim.truth import SessionStream, TruthModel, pose_drift_rms_dps

MAX_COEFF_DPS = 10.0
"""The largest coefficient magnitude the unit accepts [deg/s per term unit]; more is OUT_OF_RANGE."""

@dataclass
class Faults:
    """Misbehaviour on demand, for daemon tests. Counters count down as they fire."""

    nak_next: int = 0
    """NAK (reason BUSY) the next N coefficient writes."""
    drop_acks: int = 0
    """Apply nothing and stay silent for the next N coefficient writes."""
    never_hello: bool = False
    """Do not announce switch-on."""
    garbage_rate: float = 0.0
    """Probability per frame that the transport prepends a burst of 1..16 random bytes (serial)."""
    nan_readback: int = 0
    """The next N COEFF_REPORTs carry NaN coefficients under a valid frame CRC (a unit's bug)."""
    lose_ack: int = 0
    """Apply the next N valid writes but lose their ack (the host sees silence, the unit holds the set)."""
    cycle_after_ack: int = 0
    """Power-cycle right after the next N acks (the host may never see the read-back)."""
    no_coeff_read: bool = False
    """Never answer COEFF_READ (a listen-only replay, a unit without read-back)."""
    seq_outlier_every_s: float = 0.0
    """One sample with a far sequence number every S s of unit time (0 = never)."""
    silence_at_s: float = 0.0
    """Go silent (send nothing, answer nothing) this many s after the process started (0 = never)."""
    silence_for_s: float = 0.0
    """How long the silence lasts [s]; the sample counter keeps running meanwhile."""
    lose_burst_s: float = 0.0
    """Samples lost on the link for this long [s of unit time] in every ``lose_every_s`` (a USB-serial
    adapter that overruns, a busy CAN bus): the unit takes and counts them, the host never sees them."""
    lose_every_s: float = 0.0
    """The period of those bursts [s of unit time] (0 = never)."""


@dataclass(frozen=True)
class NanReport:
    """A COEFF_REPORT whose coefficients are NaN: no encoder produces it, so transports build the
    frames by hand (fault injection only)."""

    version: int
    terms_id: int
    n_terms: int


@dataclass(frozen=True)
class AppliedSet:
    """A coefficient set held in flash. ``coeffs_dps`` has shape (3, P) [deg/s per term unit]."""

    version: int
    terms_id: int
    names: tuple[str, ...]
    coeffs_dps: np.ndarray
    crc: int
    spec: TermSpec = field(repr=False, compare=False, default=None)  # type: ignore[assignment]

    def wire_coeffs(self) -> tuple[tuple[float, ...], ...]:
        return tuple(tuple(float(c) for c in row) for row in self.coeffs_dps)


@dataclass
class Chunk:
    """What the unit sent in one batch, with the truth beside it. Arrays have N rows."""

    seq: np.ndarray
    columns: dict[str, np.ndarray]
    """Log columns as sent (t, wx.. compensated [deg/s], ax.. [g], temp [degC], session) plus the
    truth (drift_w* [deg/s] before compensation, comp_w* [deg/s] subtracted, ref_w*, g*, still)."""

    def samples(self) -> list[Sample]:
        c = self.columns
        rows = zip(self.seq.tolist(), c["t"].tolist(), c["wx"].tolist(), c["wy"].tolist(), c["wz"].tolist(),
                   c["ax"].tolist(), c["ay"].tolist(), c["az"].tolist(), c["temp"].tolist(), strict=True)
        return [Sample(seq=s, t_s=t, gyro_dps=(wx, wy, wz), accel_g=(ax, ay, az), temp_c=tc)
                for s, t, wx, wy, wz, ax, ay, az, tc in rows]


class VirtualUnit:
    """A simulated unit following ``schedule`` with drift from ``truth``, ``rate_hz`` samples/s.

    Deterministic for a given ``seed``: each boot's bias and noise depend on (seed, boot) only.
    """

    def __init__(
        self, truth: TruthModel, schedule: Schedule, rate_hz: float, seed: int, serial: int,
        *, fw_version: str = "1.0.0", faults: Faults | None = None, boot_count: int = 0,
        applied: AppliedSet | None = None, ambients_c: tuple[float, ...] = (),
    ) -> None:
        self.truth, self.schedule, self.rate_hz = truth, schedule, float(rate_hz)
        self.ambients_c = tuple(float(a) for a in ambients_c)  # [degC] per switch-on, the last repeating
        self._boots_here = 0
        self.seed, self.serial, self.fw_version = int(seed), int(serial), fw_version
        self.faults = faults or Faults()
        self.boot_count = int(boot_count)
        self.applied: AppliedSet | None = applied
        self.stream: SessionStream | None = None
        self._trate = termsets.TempRate()
        self.samples_sent = 0
        self.writes = {"acked": 0, "naked": 0, "dropped": 0, "acks_lost": 0}
        self.cycle_pending = False  # set by the cycle_after_ack fault; the runner power-cycles

    # ---- switch-on and output ------------------------------------------------------------------
    def power_on(self) -> list[Any]:
        """Switch on: count the boot, start a new session (new bias); return the HELLO to send."""
        self.boot_count += 1
        if self.ambients_c:  # this switch-on's ambient temperature (--ambient)
            thermal = self.truth.thermal.at_boot(self.ambients_c, self._boots_here)
            self.truth = replace(self.truth, thermal=thermal)
        self._boots_here += 1
        self.stream = SessionStream(self.truth, self.schedule, self.rate_hz, self.seed, self.boot_count)
        self._trate = termsets.TempRate()  # dtemp as protocol.md defines it, from this switch-on
        return self._hello()

    def _hello(self) -> list[Any]:
        if self.faults.never_hello or self.stream is None:
            return []
        return [Hello(serial=self.serial, fw_version=self.fw_version, boot_count=self.boot_count,
                      rate_hz=int(round(self.rate_hz)))]

    @property
    def session_index(self) -> int:
        """Samples sent in this session (the next sample's index)."""
        return 0 if self.stream is None else self.stream.index

    def render(self, n: int) -> Chunk:
        """The next ``n`` samples of this session, compensated, with the truth beside them."""
        if self.stream is None:
            raise RuntimeError("the unit is off; call power_on() first")
        i0 = self.stream.index
        cols = self.stream.chunk(n)
        t_on = np.arange(i0, i0 + n) / self.rate_hz
        applied = self.applied  # one read: a set applied meanwhile takes effect at the next chunk
        dtemp = self._trate.update(cols["t"], cols["temp"])  # kept up whether or not a set uses it
        comp = np.zeros((n, 3)) if applied is None else self._compensation(applied, cols, t_on, dtemp)
        for k, a in enumerate("xyz"):
            cols[f"w{a}"] = cols[f"w{a}"] - comp[:, k]
            cols[f"comp_w{a}"] = comp[:, k]
        self.samples_sent += n
        seq = np.arange(i0, i0 + n, dtype=np.int64) % SEQ_MODULO
        return Chunk(seq=seq, columns=cols)

    def samples(self, n: int) -> list[Sample]:
        """The next ``n`` SAMPLE messages (compensated output)."""
        return self.render(n).samples()

    def _compensation(self, applied: AppliedSet, cols: dict[str, np.ndarray], t_on: np.ndarray,
                      dtemp: np.ndarray) -> np.ndarray:
        """(N, 3) [deg/s] that the applied set subtracts, from measured accel and the thermal state."""
        inputs = {"ax": cols["ax"], "ay": cols["ay"], "az": cols["az"], "temp": cols["temp"],
                  "dtemp": dtemp, "t_on": t_on, "t": cols["t"]}
        return block_terms(applied.spec, inputs) @ applied.coeffs_dps.T  # gravity = a/|a| (protocol.md)

    # ---- host requests -------------------------------------------------------------------------
    def handle(self, msg: Any) -> list[Any]:
        """Answer one message from the host; returns the replies to send (maybe none)."""
        if isinstance(msg, CoeffWrite):
            return self._write(msg)
        if isinstance(msg, HelloRequest):  # a host that started listening late: same boot count
            return self._hello()
        if isinstance(msg, CoeffTransferFailed):  # a CAN transfer that did not commit cleanly
            self.writes["naked"] += 1
            return [CoeffNak(version=msg.version, crc=msg.crc, reason=msg.reason)]
        if isinstance(msg, HelloRequest):
            # the host asks who we are: the same HELLO as at switch-on, boot counter unchanged
            if self.stream is None or self.faults.never_hello:
                return []
            return [Hello(serial=self.serial, fw_version=self.fw_version, boot_count=self.boot_count,
                          rate_hz=int(round(self.rate_hz)))]
        if isinstance(msg, CoeffRead):
            a = self.applied
            if self.faults.no_coeff_read:
                return []
            if self.faults.nan_readback > 0:
                self.faults.nan_readback -= 1
                if a is None:
                    return [NanReport(0, termsets.SEED000_ID, 10)]
                return [NanReport(a.version, a.terms_id, len(a.names))]
            if a is None:
                return [CoeffReport(version=0, terms_id=0, coeffs_dps=((), (), ()))]
            return [CoeffReport(version=a.version, terms_id=a.terms_id, coeffs_dps=a.wire_coeffs())]
        return []

    def _write(self, msg: CoeffWrite) -> list[Any]:
        f = self.faults
        if f.drop_acks > 0:
            f.drop_acks -= 1
            self.writes["dropped"] += 1
            return []
        reason = self._check(msg)
        if reason is None and f.nak_next > 0:
            f.nak_next -= 1
            reason = NakReason.BUSY
        if reason is not None:
            self.writes["naked"] += 1
            return [CoeffNak(version=msg.version, crc=_crc_or_zero(msg), reason=int(reason))]
        self.applied = self._build(msg)  # atomic apply: build the whole set, then swap one reference
        self.writes["acked"] += 1
        if f.cycle_after_ack > 0:
            f.cycle_after_ack -= 1
            self.cycle_pending = True
        if f.lose_ack > 0:
            f.lose_ack -= 1
            self.writes["acks_lost"] += 1
            return []
        return [CoeffAck(version=msg.version, crc=self.applied.crc)]

    @staticmethod
    def _build(msg: CoeffWrite) -> AppliedSet:
        names = tuple(termsets.names_for(msg.terms_id) or ())
        crc = coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps)
        coeffs = np.array(msg.coeffs_dps, dtype=np.float64).reshape(3, len(names))
        return AppliedSet(msg.version, msg.terms_id, names, coeffs, crc, TermSpec.parse(names))

    def _check(self, msg: CoeffWrite) -> NakReason | None:
        names = termsets.names_for(msg.terms_id)
        if names is None:
            return NakReason.UNKNOWN_TERMS
        rows = msg.coeffs_dps
        if len(rows) != 3 or any(len(r) != len(names) for r in rows):
            return NakReason.BAD_LENGTH
        if not all(math.isfinite(c) and abs(c) <= MAX_COEFF_DPS for r in rows for c in r):
            return NakReason.OUT_OF_RANGE
        return None

    # ---- truth for tests and the demo ----------------------------------------------------------
    def bias_dps(self) -> np.ndarray:
        """This boot's switch-on bias (3,) [deg/s]."""
        if self.stream is not None:
            return self.stream.bias_dps
        return self.truth.switch_on_bias(self.seed, self.boot_count)

    def pose_compensation_dps(self) -> np.ndarray | None:
        """The applied set's compensation at each schedule pose (K, 3) [deg/s], at ambient, settled."""
        a = self.applied
        if a is None:
            return None
        k = len(self.schedule.poses_g)
        g = self.schedule.poses_g
        inputs = {"ax": g[:, 0], "ay": g[:, 1], "az": g[:, 2],
                  "temp": np.full(k, self.truth.thermal.ambient_c),
                  "dtemp": np.zeros(k), "t_on": np.full(k, np.inf), "t": np.zeros(k)}
        with np.errstate(all="ignore"):
            return a.spec.design(inputs) @ a.coeffs_dps.T

    def status(self) -> dict[str, Any]:
        """Boot count, applied set, pose drift RMS before/after compensation [deg/s], samples sent."""
        bias = self.bias_dps()
        raw = pose_drift_rms_dps(self.truth, self.schedule, bias)
        comp = pose_drift_rms_dps(self.truth, self.schedule, bias, self.pose_compensation_dps())
        a = self.applied
        return {
            "serial": self.serial, "fw_version": self.fw_version, "boot_count": self.boot_count,
            "applied_version": None if a is None else a.version,
            "applied_terms_id": None if a is None else a.terms_id,
            "applied_terms": None if a is None else list(a.names),
            "applied_crc": None if a is None else a.crc,
            "drift_rms_raw_dps": _xyz(raw), "drift_rms_compensated_dps": _xyz(comp),
            "samples_sent": self.samples_sent, "session_samples": self.session_index,
            "rate_hz": self.rate_hz, "writes": dict(self.writes),
            "faults": asdict(self.faults),
        }

    # ---- flash persistence (optional, for a sim restarted as a new process) --------------------
    def flash_state(self) -> dict[str, Any]:
        a = self.applied
        return {"serial": self.serial, "boot_count": self.boot_count,
                "applied": None if a is None else {"version": a.version, "terms_id": a.terms_id,
                                                   "coeffs_dps": a.coeffs_dps.tolist()}}

    def load_flash(self, state: dict[str, Any]) -> None:
        self.boot_count = int(state.get("boot_count", 0))
        a = state.get("applied")
        if a:
            coeffs = tuple(tuple(float(c) for c in row) for row in a["coeffs_dps"])
            msg = CoeffWrite(version=int(a["version"]), terms_id=int(a["terms_id"]), coeffs_dps=coeffs)
            if self._check(msg) is None:
                self.applied = self._build(msg)

def _crc_or_zero(msg: CoeffWrite) -> int:
    """The CRC of the set as received, or 0 when it cannot even be encoded (NaN, wrong shape)."""
    try:
        return coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps)
    except ProtocolError:
        return 0


def _xyz(v: np.ndarray) -> dict[str, float]:
    return {a: float(v[k]) for k, a in enumerate("xyz")}
