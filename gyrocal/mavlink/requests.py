"""The daemon's requests to a MAVLink unit: ``CoeffWrite`` (the push), ``CoeffRead``, ``HelloRequest``.

A mixin of :class:`~gyrocal.mavlink.link.MavlinkLink`, kept apart so that each module holds one thing:
link.py speaks MAVLink and turns the stream into samples; this module turns the daemon's requests into
parameter transactions (gyrocal/mavlink/paramtx.py) and their outcomes into ``CoeffAck`` /
``CoeffNak`` / ``CoeffReport``, and keeps the samples consistent with what it reports (``_adjust``).
Everything here runs on the link's reader thread.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from gyrocal.errors import LinkError
from gyrocal.mavlink.paramtx import ParamPush, ParamRestore
from gyrocal.mavlink.poly import evaluate
from gyrocal.protocol.messages import (
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffWrite,
    HelloRequest,
    NakReason,
    coeff_set_crc,
)
from gyrocal.protocol.termsets import TEMP_POLY3_ID, TEMP_POLY3_TERMS

if TYPE_CHECKING:
    from gyrocal.mavlink.link import MavlinkLink

log = logging.getLogger("gyrocal.mavlink.link")

CMD_REBOOT = 246
"""MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN."""


READ_RETRIES = 3
"""Whole parameter reads tried again at a boot's start before a failed read is a fault."""

SILENT_S = 1.5
"""No heartbeat or IMU message for this long [s]: the autopilot is silent (hung, rebooting, a cable
out), so a parameter read that failed says nothing of its parameters and is tried again when it
answers (at 1 Hz heartbeats and a stream of 50 Hz or more, an autopilot that answers is heard within
1 s)."""

READ_AGAIN_S = 5.0
"""A parameter read that failed after the HELLO, the autopilot answering otherwise, is tried again
this often [s] until it succeeds (``_read_fault`` meanwhile)."""

MIN_RANGE_C = 1.0
"""The narrowest TMIN..TMAX [degC] a set with temperature terms is written with (never extrapolated)."""


class UnitRequests:
    """The request half of MavlinkLink (see the module docstring)."""

    def _serve(self: MavlinkLink, msg: Any, now: float, out: list[Any]) -> None:
        if msg == "reboot":
            if not self.armed:
                self._command(CMD_REBOOT, 1.0)
        elif isinstance(msg, HelloRequest):
            if self._hello is not None:
                out.append(self._hello)
        elif isinstance(msg, CoeffRead):
            if self.profile is None or self.fault:
                return
            self._report_wanted = True
            if self._reader is None and self._push is None and self._restore is None \
                    and self._read_again_at is None:  # else the read due then answers
                self._reader = self._read_all(now)
        elif isinstance(msg, CoeffWrite):
            self._start_push(msg, now, out)

    def _start_push(self: MavlinkLink, msg: CoeffWrite, now: float, out: list[Any]) -> None:
        crc = coeff_set_crc(msg.version, msg.terms_id, msg.coeffs_dps)
        running = self._push_write
        if (
            self._push is not None
            and running is not None
            and running.version == msg.version
            and coeff_set_crc(running.version, running.terms_id, running.coeffs_dps) == crc
        ):
            # the host resent the write it is waiting for: answered with the running push's outcome
            # (one answer per write, protocol.md), never BUSY, which made the record say nak for a
            # push that went on and was acked
            self._push_repeats += 1
            log.info("mavlink %s: v%d resent while its push runs; answered when it ends", self.url,
                     msg.version)
            return
        why, reason = self._refuse(msg)
        if why:
            # the daemon tries a BUSY set again, for as long as the autopilot stays armed or learning:
            # the same refusal of the same version is said once, then INFO (an integrator's audit)
            again = self._last_refusal == (msg.version, why)
            self._last_refusal = (msg.version, why)
            log.log(logging.INFO if again else logging.WARNING, "mavlink link: push of v%d refused%s: %s",
                    msg.version, " again" if again else "", why)
            out.append(CoeffNak(msg.version, crc, int(reason)))
            return
        lo, hi = self._push_bounds(msg)
        if self._own_range(msg.version) is not None:
            log.info("mavlink %s: v%d is written with its own range, %.1f..%.1f degC", self.url,
                     msg.version, lo, hi)
        self._push_range = (lo, hi)
        if self._own_range(msg.version) is None and self.tmin_c is None and self.tmax_c is None:
            # a retry of this version (a push cut short, BUSY) is written with this first range, the one
            # it was learnt over: written later with the wider range seen since, a v2 learnt over
            # 20-43.5 degC went to TMAX 47.1, its record still saying 43.5, and no refinement followed
            # while 300-400 deg/h were left at 50 degC (an integrator's re-check)
            self.state.keep_range(self.serial, msg.version, lo, hi)
        self._push_write = msg
        self._reader, self._check_read = None, False  # a running read (an idle check) gives way
        q = np.zeros((3, 4))
        q[:, : len(msg.coeffs_dps[0])] = np.asarray(msg.coeffs_dps)  # a shorter prefix: higher powers 0
        self._push = ParamPush(
            self.profile,
            q,
            lo,
            hi,
            self._send_param,
            now,  # type: ignore[arg-type]
            timeout_s=self.param_timeout_s,
            retries=self.param_retries,
            gate=self._clock_seen,
            expect_rotation=self._hello_rotation,
        )

    def _refuse(self: MavlinkLink, msg: CoeffWrite) -> tuple[str, NakReason]:
        if self.fault:
            return self.fault, NakReason.UNKNOWN_TERMS
        names = self.term_sets.get(msg.terms_id)
        if names is None or len(msg.coeffs_dps[0]) != len(names):
            return (
                f"terms_id 0x{msg.terms_id:04x} is not the temperature polynomial this autopilot holds "
                f"(0x{TEMP_POLY3_ID:04x}: {', '.join(TEMP_POLY3_TERMS)}, or its first 3 or 2 terms)"
            ), NakReason.UNKNOWN_TERMS
        if self.profile is None or self._hello is None:
            return "the autopilot is not identified yet", NakReason.BUSY
        if self._restore is not None:
            return "the set held before a cut push is being written back", NakReason.BUSY
        if self.profile.learning(self._params):
            return (f"the autopilot is learning its own temperature calibration ({self.profile.enable.name} "
                    "= 2): gyrocal writes nothing until it ends (it sets 1), or set 0 to let gyrocal "
                    "calibrate", NakReason.BUSY)
        if self._own_calibration:
            return ("the autopilot ended its own temperature calibration run this boot: its set stands "
                    "until the next boot", NakReason.BUSY)
        if self._read_fault is not None or self._read_again_at is not None:
            return (f"{self._read_fault or 'the autopilot was silent'}; its parameters are read again first",
                    NakReason.BUSY)
        if self.armed:
            return "the vehicle is armed; compensation is never changed in flight", NakReason.BUSY
        if self._push is not None:
            return "a push is already running", NakReason.BUSY
        lo, hi = self._push_bounds(msg)
        if not hi - lo >= MIN_RANGE_C:
            return (
                f"the temperature range seen ({lo:.1f}..{hi:.1f} degC) is too narrow",
                NakReason.OUT_OF_RANGE,
            )
        return "", NakReason.BUSY

    def _push_bounds(self: MavlinkLink, msg: CoeffWrite) -> tuple[float, float]:
        """TMIN/TMAX [degC] for ``msg``'s set: its own range (``_own_range``), else the range seen
        (``_temp_bounds``). A constant alone (its temperature terms 0: a board held at one temperature,
        session.py STEADY_S) is the same at any temperature, so a range seen narrower than MIN_RANGE_C
        is widened about its middle to MIN_RANGE_C."""
        own = self._own_range(msg.version)
        if own is not None:
            return own
        lo, hi = self._temp_bounds()
        const_only = not np.any(np.asarray(msg.coeffs_dps, dtype=np.float64)[:, 1:])
        if const_only and np.isfinite(lo) and np.isfinite(hi) and hi - lo < MIN_RANGE_C:
            mid = (lo + hi) / 2.0
            lo = float(np.floor((mid - MIN_RANGE_C / 2.0) * 10) / 10)
            hi = float(np.ceil((mid + MIN_RANGE_C / 2.0) * 10) / 10)
        return lo, hi

    def _own_range(self: MavlinkLink, version: int) -> tuple[float, float] | None:
        """The range [degC] ``version`` was learnt over, when the link keeps one and the config pins
        none: a version the autopilot held before (a rollback), or an operator's file that said it
        (``hold_range``). The range seen since may be wider: v1 of 22.4-38.0 degC went back with TMAX
        44.8, extrapolated (an integrator's audit)."""
        kept = (self.state.unit(self.serial).get("ranges") or {}).get(str(version))
        if isinstance(kept, list) and len(kept) == 2 and self.tmin_c is None and self.tmax_c is None:
            return float(kept[0]), float(kept[1])
        return None

    def _temp_bounds(self: MavlinkLink) -> tuple[float, float]:
        """TMIN/TMAX: the range seen over all boots (never extrapolate), unless the config fixes them."""
        lo, hi = self._range or [np.nan, np.nan]
        if self._hello is not None and self._range:
            lo, hi = self.state.widen(self.serial, lo, hi)
        lo = self.tmin_c if self.tmin_c is not None else lo
        hi = self.tmax_c if self.tmax_c is not None else hi
        return float(np.floor(lo * 10) / 10), float(np.ceil(hi * 10) / 10)

    def _finish_push(self: MavlinkLink, out: list[Any]) -> None:
        push, write = self._push, self._push_write
        if push is None or write is None or not push.finished or push.outcome is None:
            return
        self._push, self._push_write = None, None
        answers, self._push_repeats = 1 + self._push_repeats, 0
        res = push.outcome
        if res.params:
            self._params = {**self._params, **res.params}
        self._adj = None
        self._cut_push = None
        moved = (self.profile is not None and self._hello_rotation is not None and res.params
                 and self.profile.rotation_of(res.params) != self._hello_rotation)
        if res.ok and self.profile is not None and not moved:
            self._remember(write, res.params, res.target, self._push_range)
            rep = self._last_report = self._reported(self._params)
            ack = CoeffAck(write.version, _crc(rep))
            out.extend([ack] * answers)
            if self.reboot_required:
                log.info(  # the daemon's session logs the one WARNING (and status says so)
                    "mavlink %s: v%d is stored; %s applies it only after a reboot",
                    self.url,
                    write.version,
                    self.profile.name,
                )
        else:
            if not res.restored and res.target:
                # cut short (a reboot, silence): the autopilot may hold the whole set all the same, its
                # ENABLE = 1 written before the cut; the next read tells (_after_read)
                self._cut_push = (write, dict(res.target), self._push_range, dict(push.before))
            log.error(
                "mavlink %s: push of v%d failed: %s (%s)",
                self.url,
                write.version,
                res.reason or "the board rotation changed during the push",
                "previous set restored" if res.restored else "compensation left as read back",
            )
            reason = res.nak or int(NakReason.BUSY)
            if "no PARAM_VALUE" in (res.reason or "") and self._params:
                # parameters this boot's read found went unanswered: their answers were lost (a busy
                # downlink), the firmware has them. NAK UNKNOWN_TERMS is final, and the session pushed
                # nothing more this switch-on, the compensation left off (an integrator's audit). BUSY,
                # and the parameters are read again before the next write
                reason = int(NakReason.BUSY)
                self._read_fault = f"{self.profile.name if self.profile else 'autopilot'} parameters " \
                                   f"unanswered: {res.reason}"
                self._read_again_at = time.monotonic() + READ_AGAIN_S
            nak = CoeffNak(
                write.version,
                coeff_set_crc(write.version, write.terms_id, write.coeffs_dps),
                reason,
            )
            out.extend([nak] * answers)
        if moved:
            self._check_rotation(out)  # a new session, cold: no resend of a set of the old frame

    def _remember(self: MavlinkLink, write: CoeffWrite, params: dict[str, float],
                  target: dict[str, float], rng: tuple[float, float] | None = None) -> None:
        """The autopilot holds ``write``'s set: keep its version with the parameters that identify it,
        and the range [degC] it was written with (a rollback writes it again with that range)."""
        if self.profile is None:
            return
        u = self.state.unit(self.serial)
        if rng is not None:
            self.state.keep_range(self.serial, write.version, *rng)
        rotation = self.profile.rotation_of(params)  # the frame the set was written in
        u.update(
            version=write.version,
            coeffs=[list(r) for r in write.coeffs_dps],
            terms_id=write.terms_id,
            durable={**{k: params[k] for k in self.profile.durable if k in params}, **rotation},
            target={**target, self.profile.enable.name: 1.0},
            rotation=rotation,
        )
        self.state.save()

    def _reported(self: MavlinkLink, params: dict[str, float]) -> CoeffReport:
        """The set the unit holds, in our terms: our stored version when its parameters are intact."""
        p = self.profile
        assert p is not None
        q = p.applied(params)
        u = self.state.units.get(str(getattr(self, "serial", "")), {})
        version = 0
        durable, target = u.get("durable"), u.get("target")
        if durable and all(params.get(k) == v for k, v in durable.items()):
            version = int(u.get("version", 0))
            if target and all(params.get(k) == v for k, v in target.items()):
                # exactly what was written, in its own term set (the unit holds its float32 rounding)
                return CoeffReport(version, int(u.get("terms_id", TEMP_POLY3_ID)), u["coeffs"])
            # our set with a constant the autopilot re-measured (ArduPilot's boot gyro calibration): in
            # its own shorter term set when the powers it lacks are zero, as it was written
            tid = int(u.get("terms_id", TEMP_POLY3_ID))
            n = len(self.term_sets.get(tid, ())) or q.shape[1]
            if n < q.shape[1] and not np.any(q[:, n:]):
                return CoeffReport(version, tid, q[:, :n])
        return CoeffReport(version, TEMP_POLY3_ID, q)

    def reboot(self: MavlinkLink) -> None:
        """Ask the autopilot to reboot (MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN 1); refused while armed."""
        if self.armed:
            raise LinkError("the vehicle is armed; gyrocal never reboots an armed autopilot")
        self._requests.append("reboot")

    def _silent(self: MavlinkLink, now: float) -> bool:
        """Nothing heard from the autopilot (heartbeat or IMU message) for ``SILENT_S``."""
        heard = [t for t in (self._boot.last_hb, self._imu_rx) if t is not None]
        return not heard or now - max(heard) > SILENT_S

    def _after_read(self: MavlinkLink, out: list[Any]) -> None:
        reader, self._reader = self._reader, None
        check, self._check_read = self._check_read, False
        if reader is None or self.profile is None:
            return
        if reader.error and check and not self._report_wanted:  # a COEFF_READ waiting: its error stands
            log.debug("mavlink %s: idle parameter check failed (%s); tried again later", self.url,
                      reader.error)
            return
        if reader.error and self._hello is None and self._read_retries < READ_RETRIES:
            # a boot's first read whose echoes were lost (a busy link): read again before calling it a
            # fault, which holds until the next boot (a daemon under load never said HELLO)
            self._read_retries += 1
            log.info("mavlink %s: parameter read failed (%s); reading again (%d of %d)", self.url,
                     reader.error, self._read_retries, READ_RETRIES)
            self._reader = self._read_all(time.monotonic())
            return
        now = time.monotonic()
        if reader.error and self._silent(now):
            # cut by the autopilot's silence (a hang after a push was cut, a cable out): it says nothing
            # of the parameters. As a fault, it NAKed every later write UNKNOWN_TERMS (final) and left an
            # ArduPilot with its compensation off for the switch-on (a hang at the 23rd PARAM_SET)
            self._read_again_at = now
            log.warning("mavlink %s: parameter read cut short, the autopilot is silent (%s); read again "
                        "when it answers", self.url, reader.error)
            return
        if reader.error and self._hello is not None:
            # the autopilot answers (heartbeats, IMU) but not the parameter protocol: lost echoes, a
            # busy downlink. It read the parameters at this boot's start, so this is no configuration
            # fault: latched as one, it refused every later write and read for good, the compensation
            # left off mid-push (20 s of lost PARAM_VALUE: an integrator's audit). Read again every
            # READ_AGAIN_S; writes are NAKed BUSY meanwhile
            why = f"cannot read {self.profile.name} compensation parameters: {reader.error}"
            if why != self._read_fault:
                log.warning("mavlink %s: %s; reading again every %g s, writes wait", self.url, why,
                            READ_AGAIN_S)
            self._read_fault, self._read_again_at = why, now + READ_AGAIN_S
            return
        if reader.error:
            hint = (f"; IMU {self.instance}: does the autopilot have it? check link.mavlink.instance (0..2)"
                    if self.instance else "")
            self._set_fault(f"cannot read {self.profile.name} compensation parameters: {reader.error}{hint}")
            return
        if self._read_fault is not None:
            log.info("mavlink %s: the compensation parameters are read again", self.url)
            self._read_fault = None
        if self.profile.learning(self._params) and self.profile.is_enabled(reader.values):
            # the autopilot's own calibration run has ended (ArduPilot sets 1 when it is done): that
            # set is what its user ran the learning for, and it stands until the next boot. Replaced
            # within the second, an ArduPilot's 8/6/3 deg/h became gyrocal's 22/15/17, the learning
            # lost (an integrator's re-check)
            self._own_calibration = True
            log.warning("mavlink %s: the autopilot ended its own temperature calibration run: its set "
                        "stands until its next boot (nothing is pushed over it)", self.url)
        self._params = dict(reader.values)
        self._adj = None
        if self._boot_params is None:
            kept, self._kept_boot_params = self._kept_boot_params, None
            self._boot_params = kept if kept is not None else dict(reader.values)
        cut = self._cut_push
        if cut is not None and hasattr(self, "serial"):
            write, target, rng, before = cut
            # what identifies a set across boots (an ArduPilot re-measures INS_GYROFFS and CALTEMP)
            keys = [k for k in self.profile.durable if k in target]
            whole = bool(keys) and all(self._params.get(k) == target[k] for k in keys)
            if whole and self.profile.is_enabled(self._params):
                # its ENABLE = 1 landed before the cut (the echo was lost to a reboot): the autopilot holds
                # the whole set, so it is reported as that version and the daemon records it applied
                # (ack lost), instead of "a set gyrocal did not write" (a PX4 rebooting at the 18th write)
                log.info("mavlink %s: the autopilot holds v%d whole although its push was cut short",
                         self.url, write.version)
                self._remember(write, self._params, target, rng)
            elif before and self.profile.is_enabled(before) and not self.profile.is_enabled(self._params):
                # cut before its ENABLE = 1: the autopilot runs with its compensation off and part of
                # the new coefficients, worse than before the push; the set it held then goes back,
                # after a reboot before this boot's HELLO (the daemon's new session reads the result),
                # after a hang at once (the daemon's retry of the same version waits for it)
                log.warning("mavlink %s: the push of v%d was cut by %s before its ENABLE = 1; the "
                            "autopilot %s with its compensation off: writing back the set it held "
                            "before", self.url, write.version,
                            "a reboot" if self._hello is None else "the autopilot's silence",
                            "booted" if self._hello is None else "was left")
                self._restore = ParamRestore(self.profile, before, self._send_param, time.monotonic(),
                                             timeout_s=self.param_timeout_s, retries=self.param_retries)
            self._cut_push = None
            if self._restore is not None:
                return  # what the unit holds is read, and reported, once the restore is done
        why = self.profile.problem(self._params)
        if why:
            self._set_fault(why)
            self._config_fault = why
        elif self.fault is not None and self.fault == self._config_fault:
            # the configuration was fixed (a supported board rotation, a gyro calibration): serve again
            log.info("mavlink link: %s no longer applies", self.fault)
            self.fault = self._config_fault = None
        rep = self._reported(self._params)
        if self._report_wanted:
            self._report_wanted = False
            self._last_report = rep
            out.append(rep)
        elif check and self._hello is not None and self._last_report is not None \
                and _crc(rep) != _crc(self._last_report):
            # a ground station wrote the compensation between pushes: the daemon went on rebuilding the
            # raw rate with the set it last read, learnt a curve doubled by it and pushed a set worse
            # than none (an integrator's audit: 1607 deg/h left against 1255 uncompensated). The set
            # the autopilot holds now is reported unasked, as at a read-back
            who = "its own calibration run" if self._own_calibration else "a ground station?"
            log.log(logging.INFO if self._own_calibration else logging.WARNING,  # that one is said already
                    "mavlink %s: the autopilot's compensation changed outside gyrocal (%s): it held v%d, now "
                    "%s", self.url, who, self._last_report.version,
                    f"v{rep.version}" if rep.version else "a set gyrocal did not write (v0)")
            self._last_report = rep
            out.append(rep)
        self._check_rotation(out)

    def _check_rotation(self: MavlinkLink, out: list[Any]) -> None:
        """The board rotation read now against this boot's HELLO's: changed, the samples are in another
        body frame, so the link declares a new boot and the daemon starts a new session, cold.

        Why: a ground station writing AHRS_ORIENTATION during a push got the push NAKed, then the
        daemon's resend of the same set (learnt in the old frame) was written in the new one and
        acked: y and z compensated with the wrong sign, 336-1904 deg/h left; changed between pushes,
        nothing was said and the next set was pushed 14 s later (an integrator's audit)."""
        if self._hello is None or self._hello_rotation is None or self.profile is None:
            return
        now_rot = self.board_rotation
        if now_rot is None or now_rot == self._hello_rotation:
            return
        log.warning("mavlink %s: the board rotation changed (%s -> %s): the samples are in a new body "
                    "frame, and no set learnt in the old one is pushed; a new session starts", self.url,
                    self._hello_rotation, now_rot)
        self._new_boot(out, "the board rotation changed", real=False)

    def _adjust(self: MavlinkLink, temp_c: float) -> np.ndarray:
        """What the autopilot subtracts minus what we report it subtracts, at temp_c [deg/s].

        The polynomials are worked out once per parameter change (``_adj`` is reset whenever the
        parameters are read or written), so the per-sample cost is two cubic evaluations.
        """
        p = self.profile
        if p is None or not self._params:
            return np.zeros(3)
        if self._adj is None:
            boot = self._boot_params
            eff = boot if self.reboot_required and boot is not None else self._params
            rep = np.asarray(self._reported(self._params).coeffs_dps, dtype=np.float64)
            diff = p.applied(eff)
            diff[:, : rep.shape[1]] -= rep  # a quadratic or linear set: its missing powers are 0
            self._adj = (diff, eff)
        diff, eff = self._adj
        temps = np.array([temp_c])
        return (evaluate(diff, temps) + p.clamp_adjust(eff, temps))[0]

    # ---- time-driven steps -----------------------------------------------------------------------


def _crc(rep: CoeffReport) -> int:
    """What identifies a reported set: its CRC over version, term set and coefficients."""
    return coeff_set_crc(rep.version, rep.terms_id, rep.coeffs_dps)
