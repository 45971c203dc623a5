"""``MavlinkLink``: a PX4 or ArduPilot autopilot behind the daemon's ``Link`` seam.

It speaks MAVLink 2 on the wire (pymavlink's own connection strings: a serial device with its
``baudrate``, ``udp:``/``udpin:`` to listen, ``udpout:``, ``tcp:``) and the daemon's vocabulary
(gyrocal.protocol.messages) on the other side:

- each boot: HEARTBEAT -> AUTOPILOT_VERSION (MAV_CMD_REQUEST_MESSAGE) and the IMU stream
  (MAV_CMD_SET_MESSAGE_INTERVAL: HIGHRES_IMU, falling back to RAW_IMU/SCALED_IMUn when none comes)
  -> read the compensation parameters -> ``Hello``; then ``Sample`` per IMU message;
- ``CoeffWrite`` -> :class:`~gyrocal.mavlink.paramtx.ParamPush` -> ``CoeffAck`` / ``CoeffNak``;
- ``CoeffRead`` -> read the parameters -> ``CoeffReport``; ``HelloRequest`` -> ``Hello``.

Samples as the daemon expects them: the daemon computes ``raw = out + Q_reported(T)``. The link adds
to each sample the difference between what the autopilot really subtracts (clamped to [TMIN, TMAX],
and, for a PX4 whose TC_G_ENABLE was off at boot, nothing until the reboot) and Q_reported(T), so
that equation holds everywhere. Samples during a push are dropped (``push_gap_samples``): the
compensation changes under them parameter by parameter.

Threads: everything MAVLink happens on the reader thread (``_receive``); ``send`` only queues the
daemon's request. Capabilities: ``capabilities`` (``term_sets`` and ``reboot_required``).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any

import numpy as np

from gyrocal.daemon.capabilities import UnitCapabilities
from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers.base import ControlCallback, EventCallback, Link
from gyrocal.errors import LinkError
from gyrocal.mavlink import imu as imu_mod
from gyrocal.mavlink import pymav
from gyrocal.mavlink.paramtx import ParamPush, ParamRead, ParamReadAll, ParamRestore, ParamSet
from gyrocal.mavlink.profiles import BY_MAV_AUTOPILOT, PROFILES, Profile
from gyrocal.mavlink.requests import UnitRequests
from gyrocal.mavlink.state import LinkState
from gyrocal.protocol.messages import CoeffRead, CoeffReport, CoeffWrite, Hello, HelloRequest
from gyrocal.protocol.termsets import TEMP_POLY3_TERMS, terms_id

log = logging.getLogger(__name__)

MAV_COMP_ID_AUTOPILOT1 = 1
MAV_COMP_ID_ONBOARD_COMPUTER = 191
MAV_AUTOPILOT_INVALID = 8
MAV_MODE_FLAG_SAFETY_ARMED = 128
MSG_ID = {
    "HIGHRES_IMU": 105,
    "RAW_IMU": 27,
    "SCALED_IMU": 26,
    "SCALED_IMU2": 116,
    "SCALED_IMU3": 129,
    "AUTOPILOT_VERSION": 148,
}
CMD_SET_MESSAGE_INTERVAL, CMD_REQUEST_MESSAGE = 511, 512
TEMP_RATE_HZ = 10.0
STREAM_STALL_S = 1.0
"""IMU silence [s] with heartbeats present after which the stream is requested again."""
VERSION_ASK_S = 2.0
"""[s] AUTOPILOT_VERSION is asked for again this long after an unanswered request (before HELLO)."""
NO_IMU_FAULT = "the autopilot sends nothing of IMU "
NO_IMU_S = 10.0
"""Heartbeats but no message of the asked IMU for this long [s] after asking: a fault status names."""
NO_TEMP_FAULT = "the autopilot's IMU "
NO_TEMP_S = 10.0
"""IMU samples with no temperature for this long [s] after the HELLO are a fault the status shows."""
CHECK_EVERY_S = 10.0
"""[s] How often an idle link reads the autopilot's parameters again (board rotation, compensation)."""
FRESH_S = 0.25
"""[s] A push sends its next parameter request only after an IMU sample newer than the last answer
and younger than this (at least 5 sample periods): the autopilot's clock seen running."""


class MavlinkLink(UnitRequests, Link):
    """A link to one IMU of one autopilot. See the module docstring.

    ``autopilot``: "px4", "ardupilot" or None (take it from the heartbeat); a heartbeat of another
    kind is a fault (one error line, every CoeffWrite NAKed). ``instance``: IMU 0..2. ``rate_hz``:
    IMU stream rate asked for [Hz]. ``state_file``: where versions and boot counts persist.
    """

    kind = "mavlink"
    holds_samples_in_push = True
    """Samples are withheld while a push rewrites the compensation (``push_gap_samples``): the engine
    does not call the autopilot silent for that gap."""

    def __init__(
        self,
        url: str,
        ring: RingBuffer,
        on_control: ControlCallback,
        on_event: EventCallback | None = None,
        *,
        baudrate: int = 921600,
        autopilot: str | None = None,
        instance: int = 0,
        rate_hz: float = 250.0,
        state_file: str | None = None,
        source_system: int = 255,
        heartbeat_timeout_s: float = 3.0,
        param_timeout_s: float = 0.5,
        param_retries: int = 4,
        highres_wait_s: float = 2.0,
        tmin_c: float | None = None,
        tmax_c: float | None = None,
        **link_kwargs: Any,
    ) -> None:
        super().__init__(ring, on_control, on_event, **link_kwargs)
        if autopilot is not None and autopilot not in PROFILES:
            raise LinkError(f"mavlink link: autopilot {autopilot!r} unknown; write px4 or ardupilot")
        self.url, self.baudrate = str(url), int(baudrate)
        self.expected = autopilot
        self.instance, self.rate_hz = int(instance), float(rate_hz)
        self.source_system = int(source_system)
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.param_timeout_s, self.param_retries = param_timeout_s, param_retries
        self.highres_wait_s = highres_wait_s
        self.tmin_c, self.tmax_c = tmin_c, tmax_c
        self.state = LinkState(state_file)
        self._conn: Any = None
        self._requests: collections.deque[Any] = collections.deque()
        self.fault: str | None = None
        self._config_fault: str | None = None  # a fault of the unit's parameters, cleared when fixed
        self._mav_stats = {"frames": 0, "bytes": 0, "bad_frames": 0}
        self._extra = {"push_gap_samples": 0, "no_temperature_samples": 0, "boots_seen": 0}
        self._cut_push: tuple[CoeffWrite, dict[str, float], tuple[float, float]] | None = None
        """A push cut short: its write, target parameters and range [degC] (_after_read)."""
        self._push_range: tuple[float, float] | None = None  # TMIN, TMAX of the push running [degC]
        self._kept_boot_params: dict[str, float] | None = None  # the real boot's, over a declared one
        self._reset_boot()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop; a push under way is first let end (at most ``ack_within_s``).

        Why: the push writes ENABLE = 0 first, and a link closed in the middle left the autopilot
        with its compensation off until the next push (an ArduPilot then flies on raw gyro offsets).
        Ended, it holds the new set or the old one; the daemon's record of it stays pending and the
        next start's read-back settles it (docs/operations.md, "Faults and recovery").
        """
        push, thread = self._push, self._thread
        if push is not None and self._connected and not self._stopped and thread is not None \
                and thread.is_alive() and thread is not threading.current_thread():
            budget = self.ack_within_s
            log.warning("mavlink %s: stopping with a push under way (phase %s): letting it end, at most "
                        "%.0f s, so the autopilot is not left with its compensation off", self.url,
                        push.phase.value, budget)
            end = time.monotonic() + budget
            while self._push is push and self._connected and time.monotonic() < end:
                time.sleep(0.02)
            if self._push is push:
                log.error("mavlink %s: the push did not end within %.0f s (phase %s); the autopilot may "
                          "hold no set (ENABLE = 0) until the next push", self.url, budget,
                          push.phase.value)
            else:
                log.info("mavlink %s: the push ended (%s) before stopping", self.url,
                         "ok" if push.outcome is not None and push.outcome.ok else "failed, previous "
                         "set restored" if push.outcome is not None and push.outcome.restored else "failed")
        super().stop(timeout_s)

    # ---- capabilities (gyrocal/daemon/capabilities.py: the daemon projects its set onto them) ----
    @property
    def capabilities(self) -> UnitCapabilities:
        """What this autopilot holds (a polynomial in temperature per axis) and whether a push waits
        for a reboot, as known now (read by the daemon at each switch-on's HELLO)."""
        name = self.profile.name if self.profile is not None else "autopilot"
        return UnitCapabilities(f"mavlink {name}", tuple(self.term_sets.values()), len(TEMP_POLY3_TERMS),
                                self.reboot_required, clamps_temperature=True,
                                board_rotation=self.board_rotation, ack_within_s=self.ack_within_s,
                                own_boot_bias=bool(self.profile is not None and self.profile.own_boot_bias))

    @property
    def ack_within_s(self) -> float:
        """[s] The answer time the daemon should allow a push: room for a few lost echoes per phase
        (each costs ``param_timeout_s``), 4 x param_timeout_s x param_retries, 8 s by default.

        The 1 s of push.ack_timeout_s is our protocol unit's; a push with two lost echoes took longer,
        and the daemon's resends were NAKed BUSY ("a push is already running") while the push went on
        and was acked, so the record said nak for a set the autopilot held (an integrator's audit). A
        resend of the running push's write is now answered when the push ends, and this gives the
        daemon the time to wait for it."""
        return 4.0 * self.param_timeout_s * self.param_retries

    @property
    def board_rotation(self) -> dict[str, float] | None:
        """The board rotation parameters as last read (None before the first read): the autopilot holds
        its offsets in the sensor frame they define (docs/mavlink.md "Board rotation")."""
        if self.profile is None or not self._params:
            return None
        return self.profile.rotation_of(self._params)

    @property
    def term_sets(self) -> dict[int, tuple[str, ...]]:
        """Term sets this unit can hold: one cubic polynomial in temperature per axis, no gravity terms."""
        return {terms_id(TEMP_POLY3_TERMS[:k]): TEMP_POLY3_TERMS[:k] for k in (4, 3, 2)}

    @property
    def reboot_required(self) -> bool | None:
        """Whether a pushed set takes effect only after a reboot (None until the unit is known)."""
        if self.profile is None or self._boot_params is None:
            return None
        return self.profile.needs_reboot(self._boot_params.get(self.profile.enable.name))

    @property
    def target(self) -> str:
        return self.url

    def hold_range(self, version: int, lo_c: float, hi_c: float) -> None:
        """The temperatures [degC] an operator's set ``version`` was learnt over (`gyrocal push --file`
        of a fit or a store record): written as its TMIN..TMAX, never the range seen now, which may reach
        past it (the daemon calls this before it sends the write)."""
        if hasattr(self, "serial"):
            self.state.keep_range(self.serial, version, lo_c, hi_c, replace=True)

    # ---- Link hooks ------------------------------------------------------------------------------
    def _open(self) -> None:
        mavutil = pymav.mavutil()
        try:
            conn = mavutil.mavlink_connection(
                self.url,
                baud=self.baudrate,
                source_system=self.source_system,
                source_component=MAV_COMP_ID_ONBOARD_COMPUTER,
                autoreconnect=False,
                dialect="ardupilotmega",
            )
        except Exception as err:  # pymavlink raises serial, socket and plain errors alike
            raise LinkError(
                f"mavlink connection {self.url!r} cannot be opened ({err}); check the device "
                "path and baud rate, or the udpin:/udpout:/tcp: address"
            ) from err
        conn.mav.robust_parsing = True
        self._conn = conn
        self._reset_boot()

    def _close(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            conn.close()

    def _transmit(self, msg: Any) -> None:
        if not isinstance(msg, CoeffWrite | CoeffRead | HelloRequest):
            raise LinkError(f"mavlink link cannot send {type(msg).__name__}")
        self._requests.append(msg)

    def _decoder_stats(self) -> dict[str, int]:
        return dict(self._mav_stats)

    def _transport_stats(self) -> dict[str, Any]:
        return {
            **self._extra,
            "autopilot": self.profile.name if self.profile else None,
            "fault": self.fault,
            "read_fault": self._read_fault,
            "hold": (f"the autopilot is learning its own temperature calibration "
                     f"({self.profile.enable.name} = 2): nothing is pushed until it ends"
                     if self.profile is not None and self.profile.learning(self._params) else
                     "the autopilot ended its own temperature calibration run this boot: its set stands "
                     "until the next boot" if self._own_calibration else None),
            "imu_source": self._source,
            "reboot_required": self.reboot_required,
            "board_rotation": self.board_rotation,
        }

    def _receive(self) -> list[Any]:
        conn = self._conn
        if conn is None:
            raise OSError("connection closed")
        out: list[Any] = []
        m = conn.recv_match(blocking=True, timeout=self.poll_s)
        n = 0
        while m is not None and n < 2000:
            self._handle(m, out)
            n += 1
            m = conn.recv_msg()
        self._mav_stats["bytes"] = int(getattr(conn.mav, "total_bytes_received", 0))
        self._mav_stats["bad_frames"] = int(getattr(conn.mav, "total_receive_errors", 0))
        now = time.monotonic()
        while self._requests:
            self._serve(self._requests.popleft(), now, out)
        self._tick(now, out)
        return out

    # ---- per boot --------------------------------------------------------------------------------
    def _reset_boot(self) -> None:
        self.profile: Profile | None = PROFILES[self.expected](self.instance) if self.expected else None
        self.target_system: int | None = None
        self.armed = False
        self._boot_params: dict[str, float] | None = None
        self._params: dict[str, float] = {}
        self._adj: tuple[np.ndarray, dict[str, float]] | None = None
        self._version_msg: Any = None
        self._hello: Hello | None = None
        self._reader: ParamReadAll | None = None
        self._push: ParamPush | None = None
        self._push_write: CoeffWrite | None = None
        self._push_repeats = 0  # resends of the running push's write: each gets the push's answer
        self._restore: ParamRestore | None = None  # the set held before a push a reboot cut short
        self._read_again_at: float | None = None  # monotonic s: a failed read is tried again from then
        self._read_fault: str | None = None  # why the last read after the HELLO failed, until one succeeds
        self._own_calibration = False  # the autopilot ended its own calibration run this boot
        self._last_refusal: tuple[int, str] | None = None  # (version, why) of the last write refused
        self._last_report: CoeffReport | None = None  # the set last reported or acked, this boot
        self._report_wanted = False
        self._source: str | None = None
        self._stream_asked_at: float | None = None
        self._version_asked_at = 0.0  # when AUTOPILOT_VERSION was last asked for
        self._read_retries = 0  # this boot's first parameter read, tried again (requests.READ_RETRIES)
        self._temp_c: float | None = None
        self._no_temp_since = 0.0  # monotonic s of the first sample of this run without a temperature
        self._t_last: float | None = None
        self._imu_rx: float | None = None  # monotonic time of the last IMU message
        self._imu_n = 0  # IMU messages of this boot
        self._hello_rotation: dict[str, float] | None = None  # the board rotation at this boot's HELLO
        self._checked_at = 0.0  # monotonic time of the last idle re-read of the parameters
        self._check_read = False  # the read running is an idle check (its failure is not a fault)
        self._echo_n = 0  # _imu_n at the push's last PARAM_VALUE
        self._asked_again: float = 0.0
        self._seq = 0
        self._known_new = False
        self._range: list[float] | None = None
        self._boot = imu_mod.BootDetector(self.heartbeat_timeout_s)

    def _new_boot(self, out: list[Any], why: str, real: bool = True) -> None:
        """A new boot: everything per boot is read again and a new HELLO said. ``real=False``: the
        autopilot did not reboot, but its board rotation changed, so the samples are in a new body
        frame and the daemon must start a new session (cold, capabilities.frame_changed); the
        parameters as they were at the real boot's start (a PX4's TC_G_ENABLE) are kept."""
        log.info("mavlink %s: new boot %s (%s)", self.url, "detected" if real else "declared", why)
        if self._push is not None:
            self._push.abort(f"the autopilot rebooted ({why})" if real else why)
            self._finish_push(out)
        keep_target, keep_profile = self.target_system, self.profile
        keep_boot = None if real else self._boot_params
        keep_stream = (self._source, self._t_last, self._imu_rx) if not real else None
        self._reset_boot()
        self.target_system, self.profile = keep_target, keep_profile
        if not real:
            self._kept_boot_params = keep_boot  # taken as this boot's once its read is done (_after_read)
            self._source, self._t_last, self._imu_rx = keep_stream  # type: ignore[misc]
            self._boot.last_t = self._t_last
        if self.fault is not None:
            # a fault of the last boot (a read cut off when the autopilot vanished mid-push) is judged
            # again on this boot's reads: kept, the link never said HELLO again and the daemon sat in
            # UNIT_SILENT until restarted (an integrator's audit). A wrong autopilot type is set
            # again by the next heartbeat, a parameter problem by the next read.
            log.info("mavlink %s: the last boot's fault (%s) is checked again on this boot", self.url,
                     self.fault)
            self.fault = self._config_fault = None
        self._known_new = True
        self._extra["boots_seen"] += 1

    def _handle(self, m: Any, out: list[Any]) -> None:
        kind = m.get_type()
        if kind == "BAD_DATA":
            return
        self._mav_stats["frames"] += 1
        now = time.monotonic()
        if kind == "HEARTBEAT":
            self._on_heartbeat(m, now, out)
            return
        if self.target_system is None or m.get_srcSystem() != self.target_system:
            return
        if kind == "PARAM_VALUE":
            name = m.param_id if isinstance(m.param_id, str) else m.param_id.decode("ascii", "replace")
            name = name.rstrip("\x00")
            job = self._push or self._restore or self._reader
            if self._push is not None:
                self._echo_n = self._imu_n
            if job is not None:
                job.on_value(name, float(m.param_value), int(m.param_type), now)
            elif name in self._params and self._hello is not None:
                # unasked: an autopilot broadcasts every change, a ground station's too. A changed
                # compensation parameter is read at once (with the rest), not at the next 10 s check:
                # samples meanwhile are rebuilt with the set the daemon last read
                self._checked_at = 0.0
        elif kind == "AUTOPILOT_VERSION":
            self._version_msg = m
        elif kind == "COMMAND_ACK":
            if m.command == CMD_SET_MESSAGE_INTERVAL and m.result != 0 and self._source is None:
                self._fallback(now)
        else:
            self._on_imu(m, kind, now, out)

    def _on_heartbeat(self, m: Any, now: float, out: list[Any]) -> None:
        if m.get_srcComponent() != MAV_COMP_ID_AUTOPILOT1 or m.autopilot == MAV_AUTOPILOT_INVALID:
            return  # a ground station, a camera, another companion
        if self.target_system is None:
            self.target_system = m.get_srcSystem()
        elif m.get_srcSystem() != self.target_system:
            return
        seen = BY_MAV_AUTOPILOT.get(int(m.autopilot))
        if seen is None or (self.expected is not None and seen != self.expected):
            self._set_fault(
                f"the autopilot at {self.url} reports MAV_AUTOPILOT {m.autopilot} "
                f"({seen or 'unsupported'}); this link is configured for {self.expected or 'px4/ardupilot'}"
            )
            return
        if self.profile is None:
            self.profile = PROFILES[seen](self.instance)
        was_armed, self.armed = self.armed, bool(m.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        if self.armed and not was_armed and self._push is not None and not self._push.finished:
            # armed mid-push: no further write, so compensation is not changed in flight from here on
            # (it wrote the set to the end and acked it while armed: an integrator's audit). What the
            # autopilot holds is read back; the daemon's resend is refused until it is disarmed.
            self._push.abort("the vehicle armed during the push: no further write in flight; "
                             "compensation left as it was when it armed")
            self._finish_push(out)
        if self._boot.on_heartbeat(now):
            self._new_boot(out, "heartbeat returned after silence")
        if self._stream_asked_at is None:
            self._ask_identity_and_stream(now)

    def _set_fault(self, why: str) -> None:
        if self.fault != why:
            log.error("mavlink link: %s", why)
            self._emit("unit_error", why)
        self.fault = why

    def _ask_identity_and_stream(self, now: float) -> None:
        self._stream_asked_at = self._version_asked_at = now
        self._command(CMD_REQUEST_MESSAGE, MSG_ID["AUTOPILOT_VERSION"])
        self._ask_streams()
        self._reader = self._read_all(now)

    def _read_all(self, now: float) -> ParamReadAll:
        """A read of every parameter of the profile, with this link's timeout and retries."""
        return ParamReadAll(self.profile, self._send_param, now,  # type: ignore[arg-type]
                            timeout_s=self.param_timeout_s, retries=self.param_retries)

    def _ask_streams(self) -> None:
        temp_msg = imu_mod.temp_message(self.profile.name, self.instance)  # type: ignore[union-attr]
        if self._source in (None, "HIGHRES_IMU"):
            self._command(CMD_SET_MESSAGE_INTERVAL, MSG_ID["HIGHRES_IMU"], 1e6 / self.rate_hz)
        rate = self.rate_hz if self._source == temp_msg else TEMP_RATE_HZ
        self._command(CMD_SET_MESSAGE_INTERVAL, MSG_ID[temp_msg], 1e6 / rate)

    def _fallback(self, now: float) -> None:
        temp_msg = imu_mod.temp_message(self.profile.name, self.instance)  # type: ignore[union-attr]
        log.info("mavlink %s: no HIGHRES_IMU; using %s, asked for at %.0f Hz (the rate measured is in "
                 "status)", self.url, temp_msg, self.rate_hz)
        self._source = temp_msg
        self._command(CMD_SET_MESSAGE_INTERVAL, MSG_ID[temp_msg], 1e6 / self.rate_hz)

    def _command(self, cmd: int, *params: float) -> None:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self._conn.mav.command_long_send(self.target_system or 1, MAV_COMP_ID_AUTOPILOT1, cmd, 0, *p)

    def _send_param(self, req: object) -> None:
        tgt = self.target_system or 1
        if isinstance(req, ParamSet):
            self._conn.mav.param_set_send(
                tgt, MAV_COMP_ID_AUTOPILOT1, req.name.encode("ascii"), req.wire, req.ptype
            )
        elif isinstance(req, ParamRead):
            self._conn.mav.param_request_read_send(tgt, MAV_COMP_ID_AUTOPILOT1, req.name.encode("ascii"), -1)

    # ---- samples ---------------------------------------------------------------------------------
    def _on_imu(self, m: Any, kind: str, now: float, out: list[Any]) -> None:
        if self.profile is None:
            return
        temp_msg = imu_mod.temp_message(self.profile.name, self.instance)
        if kind not in ("HIGHRES_IMU", temp_msg):
            return
        if kind == "HIGHRES_IMU" and self.instance != 0 and self.profile.name == "px4":
            return  # PX4's HIGHRES_IMU is the primary IMU; other instances come as SCALED_IMU2/3
        r = imu_mod.decode(m)
        if r is None:
            return
        if not any(r.gyro_dps) and not any(r.accel_g):
            # ArduPilot sends SCALED_IMU2/3 all zero for an IMU it does not have: no such IMU, not a
            # unit at 0 g (there is always gravity)
            self._extra["all_zero_messages"] = self._extra.get("all_zero_messages", 0) + 1
            return
        if self.fault is not None and self.fault.startswith(NO_IMU_FAULT):
            log.info("mavlink %s: IMU %d's messages arrive", self.url, self.instance)
            self.fault = None
        if self._boot.on_time(r.t_s):
            self._new_boot(out, "boot time went back")
            self._stream_asked_at = None
            self._ask_identity_and_stream(now)
        self._t_last = r.t_s
        self._imu_rx = now
        self._imu_n += 1
        if self._push is not None:
            self._push.tick(now)  # a request the boot gate holds goes now
            self._finish_push(out)
        if kind == temp_msg and r.temp_c is not None:
            self._temp_c = r.temp_c
        if self._source is None and kind == "HIGHRES_IMU":
            self._source = "HIGHRES_IMU"
        if kind != self._source:
            return
        self._seq += 1
        if self._hello is None:
            return
        if self._temp_c is None:
            self._extra["no_temperature_samples"] += 1
            self._no_temp_since = self._no_temp_since or now
            if now - self._no_temp_since > NO_TEMP_S and self.fault is None:
                # SCALED_IMU/RAW_IMU temperature 0 is "not provided" (common.xml): every sample was
                # dropped and status said "learning the unit's noise level" for good (an audit)
                why = (f"{NO_TEMP_FAULT}{self.instance} reports no temperature ({temp_msg}.temperature "
                       f"= 0, 'not provided') for {NO_TEMP_S:g} s: its thermal compensation cannot work, "
                       "and gyrocal has no temperature to learn it over")
                self._set_fault(why)
            return
        if self.fault is not None and self.fault.startswith(NO_TEMP_FAULT) and self._no_temp_since:
            log.info("mavlink %s: the IMU reports a temperature again", self.url)
            self.fault = None
        self._no_temp_since = 0.0
        if self._push is not None:
            self._extra["push_gap_samples"] += 1
            return
        t = self._temp_c
        self._range = [min(self._range[0], t), max(self._range[1], t)] if self._range else [t, t]
        adj = self._adjust(t)
        gyro = tuple(float(g + a) for g, a in zip(r.gyro_dps, adj, strict=True))
        out.append(imu_mod.to_sample(self._seq - 1, imu_mod.ImuReading(r.t_s, gyro, r.accel_g, t), t))  # type: ignore[arg-type]

    def _tick(self, now: float, out: list[Any]) -> None:
        if (
            self._boot.last_hb is not None
            and now - self._boot.last_hb > self.heartbeat_timeout_s
            and self._hello is not None
            and self._push is not None
        ):
            self._push.abort("heartbeat lost")
            self._finish_push(out)
        if (
            self._imu_rx is not None
            and now - self._imu_rx > STREAM_STALL_S
            and now - self._asked_again > 1.0
            and self._boot.last_hb is not None
            and now - self._boot.last_hb < self.heartbeat_timeout_s
        ):
            # heartbeats but no IMU stream: a rebooted autopilot forgets SET_MESSAGE_INTERVAL. Asking
            # again is harmless, and the resumed stream's time stamps show whether it was a new boot.
            self._asked_again = now
            self._ask_streams()
        if (
            self._source is None
            and self._stream_asked_at is not None
            and now - self._stream_asked_at > self.highres_wait_s
            and self.profile is not None
        ):
            self._fallback(now)
        if (self._imu_rx is None and self._stream_asked_at is not None and self.fault is None
                and now - self._stream_asked_at > NO_IMU_S and self.profile is not None
                and self._boot.last_hb is not None and now - self._boot.last_hb < self.heartbeat_timeout_s):
            # heartbeats, but none of the asked IMU's messages: an IMU the autopilot does not have (a
            # one-IMU ArduPilot sends no SCALED_IMU2). WAIT_HELLO "0 samples received" sent the
            # operator to the cable (an integrator's audit)
            msg = imu_mod.temp_message(self.profile.name, self.instance)
            self._set_fault(f"{NO_IMU_FAULT}{self.instance}: no HIGHRES_IMU or {msg} for {NO_IMU_S:g} s, "
                            "although the autopilot answers and was asked for them: does it have that "
                            "IMU? check link.mavlink.instance (0..2)")
        if self._push is not None:
            self._push.tick(now)
            self._finish_push(out)
        if self._restore is not None:
            self._restore.tick(now)
            if self._restore.finished:
                done, self._restore = self._restore, None
                self._params.update(done.io.values)  # as confirmed by the echoes, until the re-read
                self._adj = None
                if done.ok:
                    log.info("mavlink %s: the set held before the cut push is back (ENABLE = 1%s)", self.url,
                             "; a PX4 applies it at its next reboot" if self.reboot_required else "")
                else:
                    log.error("mavlink %s: the set held before the cut push could not be written back "
                              "(%s): compensation stays off until the next push", self.url, done.error)
                self._reader = self._read_all(now)
        if (self._read_again_at is not None and now >= self._read_again_at and self._reader is None
                and self._push is None and self._restore is None and not self._silent(now)
                and self._clock_seen(now)):
            self._read_again_at = None
            log.info("mavlink %s: reading the autopilot's parameters again", self.url)
            self._reader = self._read_all(now)
        if self._reader is not None:
            self._reader.tick(now)
            if self._reader.finished:
                self._after_read(out)
        if (self._hello is None and self._version_msg is None and self._stream_asked_at is not None
                and now - self._version_asked_at > VERSION_ASK_S and self.profile is not None):
            # the answer was lost (a busy link, a pty that drops bytes when full): without it no HELLO
            # is ever said, and the daemon waited for one forever (seen in CI under load)
            self._version_asked_at = now
            self._command(CMD_REQUEST_MESSAGE, MSG_ID["AUTOPILOT_VERSION"])
        if self._hello is None and self._ready():
            self._say_hello(out)
        elif (self._hello is not None and self._push is None and self._reader is None
              and self.fault is None and now - self._checked_at > CHECK_EVERY_S):
            # read the parameters again while idle: a ground station may have changed the board
            # rotation (the samples then come in a new body frame) or the compensation itself
            self._checked_at, self._check_read = now, True
            self._reader = self._read_all(now)

    def _clock_seen(self, now: float) -> bool:
        """The push's boot gate: an IMU sample arrived after the autopilot's last answer, recently,
        and its time stamp did not go back (``_on_imu`` turns one that did into a new boot first).

        Why: a reboot mid-push is silent for about as long as one request's timeout, and the resent
        request lands in the new boot. Without the gate a PX4 took the rest of the set there, the
        read-back matched, and the push was acked as stored; but that boot had begun with TC_G_ENABLE
        = 0 (written first), so it applied nothing, and the daemon believed it (an integrator's audit,
        ``--reboot-after-sets 5``). The restarted stream's first time stamp tells the boot.
        """
        fresh = max(FRESH_S, 5.0 / self.rate_hz)
        return self._imu_rx is not None and self._imu_n > self._echo_n and now - self._imu_rx < fresh

    def _ready(self) -> bool:
        return (
            self.profile is not None
            and self._version_msg is not None
            and self._boot_params is not None
            and self._t_last is not None
            and self.fault is None
            and self._restore is None  # the new session reads what the restore leaves
        )

    def _say_hello(self, out: list[Any]) -> None:
        v = self._version_msg
        self.serial = imu_mod.derive_serial(
            int(v.uid), list(getattr(v, "uid2", []) or []), self.instance, self.target_system or 0
        )
        boot_wall = time.time() - float(self._t_last or 0.0)
        boots = self.state.note_boot(self.serial, boot_wall, known_new=self._known_new)
        # the parameters as they were when this boot began decide what the autopilot applies (a PX4
        # with TC_G_ENABLE off at boot applies nothing until its reboot). A daemon restarted in the
        # same boot read them after its own writes: the PX4 then looked as if it applied v1, the link
        # stopped correcting the samples, and the next set was learnt on that (an autopilot
        # integrator's audit: 1252 deg/h left after the reboot). So they are kept per boot.
        self._boot_params = self.state.boot_params(self.serial, boots, self._boot_params or {})
        self._adj = None
        self._hello = Hello(
            self.serial, imu_mod.fw_text(v.flight_sw_version), boots, int(round(self.rate_hz))
        )
        self._hello_rotation = self.board_rotation
        self._checked_at = time.monotonic()
        log.info(
            "mavlink %s: %s unit %d (uid %x, IMU %d), boot %d, reboot needed for a push: %s",
            self.url,
            self.profile.name,
            self.serial,
            int(v.uid),
            self.instance,
            boots,
            self.reboot_required,
        )  # type: ignore[union-attr]
        out.append(self._hello)
