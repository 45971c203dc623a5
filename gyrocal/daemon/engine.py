"""The daemon's engine: who owns what, and the estimator loop.

Threads and ownership (the one place this is written down):

- **Link reader thread** (drivers/): owns the serial port or CAN bus. It decodes frames, pushes
  SAMPLEs into the ring buffer, and posts every other frame and link event to ``inbox``.
- **Engine loop** (this module, the main thread): owns the session, the estimator, the still
  detector and all writes to the calibration store. It pops samples from the ring, drains
  ``inbox``, sends frames through ``link.send`` (the link serialises writes with its own lock),
  pings the systemd watchdog, and publishes ``status`` as a new dict each round.
- **Control server thread** (control.py): answers ``status`` from the last published dict (a
  reference swap, atomic under the GIL) and hands every other command to the engine through
  ``inbox`` with a reply slot, so only the engine loop ever mutates the session.
- **Signal handlers** (run in the main thread between bytecodes) only set flags or post to ``inbox``.

Shared mutable state is therefore limited to the ring buffer (single producer, single consumer) and
two thread-safe queues. A stuck engine loop stops pinging the watchdog and systemd restarts it.

Containment (issue 8): the loop never exits on a fault. Every handler (a sample block, a unit
message, a link event, a command, a tick, a reload) runs inside ``_contain``: an exception is
logged once per kind (then every 1000th) and counted in ``status.loop_errors``; the loop goes on.
The link is opened with ``wait=False`` by ``gyrocal run``: the daemon starts, sends READY and feeds
the watchdog without the unit, says "waiting for the unit" (state WAIT_UNIT), and the reader thread
connects when the device appears. Stream order is exact: samples are popped up to the ring index
at which the next unit message arrived, so a HELLO splits the samples of two switch-ons exactly.
Liveness: the age of the newest sample is in status; after ``SILENT_AFTER_S`` without one the
state is UNIT_SILENT (one log line on the transition, one on recovery, and in systemd's STATUS=).
"""

from __future__ import annotations

import logging
import os
import queue
import re
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gyrocal import pidlock
from gyrocal.daemon.capabilities import frame_changed, of_link
from gyrocal.daemon.commands import CommandsMixin
from gyrocal.daemon.config import DaemonConfig
from gyrocal.daemon.control import ControlServer
from gyrocal.daemon.learner import make_learner
from gyrocal.daemon.notify import Notifier
from gyrocal.daemon.reconcile import close_abandoned
from gyrocal.daemon.restart import SeqTracker
from gyrocal.daemon.ring import RingBuffer
from gyrocal.daemon.sensorcheck import SensorCheck
from gyrocal.daemon.session import Session, same_boot
from gyrocal.daemon.stillness import RETIRED_FIELDS, StillDetector
from gyrocal.daemon.store import CalibrationStore, set_io_beat
from gyrocal.daemon.tempcheck import TEMP_MAX_C, TEMP_MIN_C, TemperatureCheck
from gyrocal.drivers import open_link
from gyrocal.errors import GyrocalError
from gyrocal.protocol import termsets
from gyrocal.protocol.messages import SEQ_MODULO, Hello, HelloRequest
from gyrocal.readers.plausible import within_range

log = logging.getLogger("gyrocal.engine")
_COUNTS = re.compile(r"\d+(\.\d+)?")
"""Numbers in a status line: a line that differs only in them is the same kind of news."""

SILENT_AFTER_S = 2.0
"""No sample for this long [s] on a connected link: the unit is silent (vanished, stalled, or a
CAN bus on which it no longer sends). A unit at >= 10 Hz sends 20 samples in that time."""

IDLE_SLEEP_S = 0.01
"""A round of the loop that handled fewer than 64 samples then waits this long [s] for the ring to
fill: at 2 kHz the next round finds ~20 samples or more. The cost of a round is mostly fixed (the
still detector's windows span ``still.window_s`` whatever the block size, plus numpy's per-call
overhead): at 2 kHz on a pty, rounds every 2 ms cost the engine thread 1.8 s of CPU per 10 s,
every 10 ms 1.0 s, for a few ms more of a sample-to-weights latency of ~200 ms (the still
detector's look-ahead; benchmarks/bench_daemon.py). Unit messages and commands wait at most this
long more (the default push ack timeout is 1 s)."""

RECONNECT_MAX_S = 1.0
"""Cap on the link's reconnect back-off [s] (the config's ``link.reconnect_max_s`` may only lower it):
recovery after the unit returns must take at most ~2 s on every transport."""

ADOPT_WINDOW_S = 5.0
"""A HELLO this soon [s] after the sample sequence already showed a restart confirms that restart:
it names the session's boot, it does not start a second one."""


@dataclass
class Reply:
    """A reply slot for a control command handed to the engine loop."""

    event: threading.Event = field(default_factory=threading.Event)
    value: dict[str, Any] = field(default_factory=dict)


REJECTIONS = ("crc_errors", "oversize", "length_errors", "garbage_bytes", "unknown_types", "incomplete",
              "bad_values", "implausible", "repeated", "conflicting")
"""The link's counters of what it dropped (DecoderStats): summed up in one line a minute."""


class Engine(CommandsMixin):
    """Joins one link to sessions, the store, the control socket and systemd."""

    HELLO_ASKS_BEFORE_ADVICE = 3
    """Unanswered HELLO_REQUESTs (2 s apart) before WAIT_HELLO advises a power cycle."""
    ERRORS_SAY_S = 60.0
    """At most one line per this many seconds [s] on what the link dropped (``_say_link_errors``)."""

    def __init__(self, cfg: DaemonConfig, link_cfg: dict[str, Any] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.clock = clock  # [s]; `gyrocal replay` runs the loop on the recording's unit time
        self.inbox: queue.Queue[tuple[Any, ...]] = queue.Queue()
        self.ring = RingBuffer(1 << 16)
        self.store = CalibrationStore(cfg.state_dir)
        self.notifier = Notifier()
        self.link_cfg = link_cfg or dict(cfg.link)
        self.link: Any = None
        self.control: ControlServer | None = None
        self.session: Session | None = None
        self.last_hello: Hello | None = None
        self.detector = self._new_detector(1000.0)
        self.rate_hz: float | None = None  # measured from the samples' time stamps
        self.last_reload: dict[str, Any] | None = None  # the last SIGHUP's result, for status
        self._lock_fh: Any = None  # <state_dir>/daemon.lock, locked while this daemon runs
        self._lock_missing = False  # it could not be made at start: tried again (_retry_lock)
        self._next_lock_try = 0.0
        self._rate_dts: deque[float] = deque(maxlen=self.RATE_WINDOW)
        self._rate_last: tuple[int, float] | None = None  # seq, t [s] of the last sample measured
        self._session_from_hello = False  # the session's start was a HELLO of the unit's (same_boot)
        self._link_up_at: float | None = None  # when the link last came up [s, the engine's clock]
        self._flaps: deque[float] = deque()  # times of the link's losses in the last FLAP_WINDOW_S
        self._ups_since_said = 0  # link_up events since _say_link_errors last ran
        self._reconnect_why = ""  # the last reconnect failure's cause, its numbers masked
        self._reconnect_detail: str | None = None  # the last reconnect failure, while the link is down
        self._flap_said_at = -1e9
        self.status: dict[str, Any] = {"state": "STARTING"}
        self.started = clock()
        self.dropped_nonfinite = 0
        self.dropped_out_of_range = 0  # samples beyond what the wire carries (readers/plausible.py)
        self.temp_check = TemperatureCheck()  # daemon/tempcheck.py: temperatures no sensor reads
        self._temp_blind_since: float | None = None  # every sample since then dropped for its temperature
        self.sensor_check = SensorCheck()  # daemon/sensorcheck.py: a stuck gyro, an accelerometer not at 1 g
        self._io_beat_at = -1e9  # monotonic [s] of the last watchdog ping from a store write
        self._temp_said: tuple[float, int] = (-1e9, 0)  # when the last WARNING of them was, and the count
        self._temp_last_dropped_c = 0.0  # the last temperature dropped [degC]
        self.samples_before_hello = 0
        self.sessions_started = 0
        self.push_results: list[dict[str, Any]] = []
        self._stop = threading.Event()
        self.seq = SeqTracker()
        self.loop_errors = 0
        self._error_counts: dict[str, int] = {}
        self._last_sample_at: float | None = None  # host monotonic time of the newest sample [s]
        self._silent = False
        self._seq_session_at: float | None = None  # when a session was started by the seq alone
        self._link_state = "not opened"
        self._pending: list[tuple[Any, ...]] = []  # inbox items not handled yet, in arrival order
        self._signalled: deque[str] = deque()  # what the signal handlers asked for; see install_signals
        self._last_status_line = ""
        self._last_logged_kind = ""
        self._hello_asks = 0  # HELLO_REQUESTs sent since the last HELLO
        self._next_hello_request = 0.0
        self._errors_said: dict[str, int] = {}  # the link's rejection counters at the last summary
        self._next_errors_check = 0.0
        self._next_publish = 0.0
        self._seq_hist: deque[tuple[int, np.ndarray]] = deque(maxlen=8)
        # sample-to-weights latency [s]: a fixed-size reservoir of the newest values (O(1) memory)
        self._lat = np.full(1 << 14, np.nan)
        self._lat_i = 0
        self.idle_sleep_s = IDLE_SLEEP_S  # `gyrocal replay` sets 0: nothing arrives while it sleeps

    # -- lifecycle ----------------------------------------------------------------------------
    def _new_detector(self, rate_hz: float) -> StillDetector:
        for key, instead in RETIRED_FIELDS.items():
            if self.cfg.still.get(key) is not None:
                log.warning("%s: still.%s is ignored: the still detector's thresholds are relative "
                            "now; use %s", self.cfg.source, key, instead)
        return StillDetector.for_rate(rate_hz, self.cfg.still)

    def _driver_cfg(self) -> dict[str, Any]:
        """The drivers' config mapping from the daemon's ``link`` section."""
        c = self.link_cfg
        backoff = {"backoff_max_s": min(float(c.get("reconnect_max_s", RECONNECT_MAX_S)), RECONNECT_MAX_S)}
        if c["kind"] == "can":
            return {"kind": "can", "bus": dict(c["can"]), "node_id": int(c.get("can_node_id", 0)), **backoff}
        if c["kind"] == "mavlink":  # options under link.mavlink; docs/mavlink.md
            mav = {"state_file": str(self.cfg.state_dir / "mavlink.json"), **dict(c.get("mavlink") or {})}
            return {"kind": "mavlink", "url": c["url"], "baudrate": int(c.get("baudrate", 921600)), **mav,
                    **backoff}
        return {"kind": "serial", "url": c["url"], "baudrate": int(c.get("baudrate", 921600)), **backoff}

    def open(self, wait: bool = True) -> None:
        """Open the link (``wait=False``: start without the unit; the reader thread keeps trying)."""
        if self.cfg.watchdog and self.notifier.watchdog_interval_s() is not None:
            set_io_beat(self._io_beat)  # a slow disk's fsyncs keep the watchdog fed (store.IO_BEAT)
        self._lock_state_dir()
        self._tidy_store()
        self.link = open_link(self._driver_cfg(), self.ring, self._on_control, self._on_event,
                              where=f"{self.cfg.source}: link", start=False)
        self.link.start(wait=wait)
        self._ask_hello(self.clock())
        self.control = ControlServer(self.cfg.control_socket, self._on_command)
        self.control.start()
        log.info("control socket %s; state directory %s", self.cfg.control_socket, self.cfg.state_dir)
        self.notifier.ready()
        self.notifier.status("waiting for the unit" if not self.link.connected
                             else "waiting for the unit's HELLO")

    def _lock_state_dir(self) -> None:
        """One daemon per store: an exclusive lock on ``<state_dir>/daemon.lock``, held while it runs.

        Why: a second daemon (an operator's by hand beside the service, with its own control socket)
        opened the same serial port and warm-started from the same store: both flapped link_lost /
        link_up 4 times a second and shared the version counter (two outside audits). A state
        directory that cannot be written is reported by the store as ever; no lock is taken then.
        """
        path = self.cfg.state_dir / "daemon.lock"
        try:
            self.cfg.state_dir.mkdir(parents=True, exist_ok=True)
            fh, holder = pidlock.take(path)
        except OSError as err:
            log.warning("state directory %s: no lock file (%s): a second daemon on this store would not "
                        "be refused; tried again every %g s", self.cfg.state_dir, err.strerror or err,
                        self.LOCK_RETRY_S)
            self._lock_missing = True
            return
        if fh is None:
            raise GyrocalError(f"another gyrocal daemon ({holder}) uses the state directory "
                               f"{self.cfg.state_dir}: one daemon per store; stop it first (systemctl stop "
                               "gyrocal) or give this one its own state_dir (config) or --state-dir")
        self._hold_lock(fh)

    def _hold_lock(self, fh: Any) -> None:
        """Keep the lock just taken (``fh``) for the daemon's life, with its pid written in it."""
        self._lock_missing = False
        try:
            pidlock.write_pid(fh)
        except OSError as err:  # a full disk: the lock holds without the pid (a traceback and exit 1 was
            # a restart loop every 5 s that never calibrated: an operator's audit)
            log.warning("state directory %s: the lock is held but its pid not written (%s)",
                        self.cfg.state_dir, err.strerror or err)
        self._lock_fh = fh

    LOCK_RETRY_S = 5.0
    """[s] Between tries at the state directory's lock when it could not be made (a read-only store at
    start): once the store was writable, the lock was never taken, and a second daemon on the same
    store was not refused (an integrator's fault campaign, F5)."""

    def _retry_lock(self, now: float) -> None:
        """Take the state directory's lock once it can be made; one line when taken, one ERROR if
        another daemon holds it by then (it started while this one could not lock)."""
        if not self._lock_missing or now < self._next_lock_try:
            return
        self._next_lock_try = now + self.LOCK_RETRY_S
        try:
            fh, holder = pidlock.take(self.cfg.state_dir / "daemon.lock")
        except OSError:
            return  # still not writable: said at start
        if fh is None:
            self._lock_missing = False
            log.error("state directory %s: another gyrocal daemon (%s) took it while this one could not "
                      "lock it: two daemons share the store; stop one (systemctl stop gyrocal)",
                      self.cfg.state_dir, holder)
            return
        self._hold_lock(fh)
        log.info("state directory %s: locked (daemon.lock) now that it can be written", self.cfg.state_dir)

    def _tidy_store(self) -> None:
        """At start (the only writer now): remove temporaries of interrupted writes, close abandoned
        pushes, prune each unit's history to store.keep_versions. This runs before READY=1, while
        systemd's start timeout (90 s) and not its watchdog (10 s) applies: a store grown over years
        takes seconds to read and to prune (docs/operations.md). A store that cannot be written is
        reported, never fatal (the session retries)."""
        try:
            self.store.clean_leftovers()
            close_abandoned(self.store)
        except Exception as err:
            log.error("calibration store: start-up tidy failed: %s", err)
        for serial in self.store.units():
            self._prune_store(serial)
            self._register_stored_terms(serial)

    def _register_stored_terms(self, serial: int) -> None:
        """The term sets of a unit's stored versions (an operator's `push --file` of a set beyond the
        config's): the unit reports by terms id, and a read-back of a set whose names this process
        does not know is refused, so a restarted daemon would count samples and never learn."""
        try:
            recs = self.store.history(serial)
        except Exception:
            return
        for rec in recs:
            try:
                termsets.register_unit_terms(rec.terms)
            except Exception as err:
                log.debug("unit %d v%d: terms not registered: %s", serial, rec.version, err)

    def _prune_store(self, serial: int) -> None:
        """Keep the newest store.keep_versions of a unit (CalibrationStore.prune); never fatal."""
        try:
            self.store.prune(serial, int(self.cfg.store["keep_versions"]))
        except Exception as err:
            log.error("calibration store: unit %d: pruning old versions failed: %s", serial, err)

    IO_BEAT_S = 1.0
    """Least time [s] between two watchdog pings from the store's fsyncs."""

    def _io_beat(self) -> None:
        """WATCHDOG=1 from inside a store write: the loop waits on the disk, alive (store.IO_BEAT)."""
        t = time.monotonic()
        if t - self._io_beat_at >= self.IO_BEAT_S:
            self._io_beat_at = t
            self.notifier.watchdog()

    def close(self) -> None:
        set_io_beat(None)
        self.notifier.stopping()
        s = self.session
        if s is not None and s.push is not None:  # its record stays 'pending' (nothing is lost)
            log.warning("stopping with the push of v%d under way: its record stays pending; the next "
                        "start closes it as abandoned, and the unit's read-back says whether it applied it",
                        s.push.write.version)
        if s is not None and s.unrecorded:
            s._flush_unrecorded(time.monotonic())  # a last try: the store may be back
        if s is not None and s.unrecorded:
            # an acked result held in memory went with the process without a word (an integrator's
            # fault campaign, F1); the next start's read-back settles the record from the unit
            log.warning("stopping with %d push result(s) the store could not take (%s): their records "
                        "stay as they were; the unit's read-back at the next start settles them",
                        len(s.unrecorded), ", ".join(f"v{v} {p.get('status')}" for v, p in s.unrecorded))
        if self.control is not None:
            self.control.stop()
        if self.link is not None:
            self.link.stop()
        fh, self._lock_fh = self._lock_fh, None
        if fh is not None:
            fh.close()  # the lock goes with it
        log.info("stopped")

    def stop(self) -> None:
        self._stop.set()

    def install_signals(self) -> None:
        """SIGTERM/SIGINT stop, SIGHUP reloads the config, SIGUSR1 recalibrates.

        A Python signal handler runs on the main thread between two bytecodes, which can be inside
        ``inbox.get_nowait()`` with the queue's lock held. A handler that put into the inbox then
        waited for that lock forever: the loop, the watchdog pings and the reload all stopped (a
        SIGHUP that hung the daemon, once in about 20 CI runs). The handlers now only append to a
        deque, which takes no lock, and the loop turns that into work (``_take_signals``).
        """
        for signum, what in ((signal.SIGTERM, "stop"), (signal.SIGINT, "stop"),
                             (signal.SIGHUP, "reload"), (signal.SIGUSR1, "recalibrate")):
            signal.signal(signum, lambda *_, what=what: self._signalled.append(what))

    def _take_signals(self) -> None:
        """Turn what the signal handlers asked for into loop work, in the order it was asked."""
        while self._signalled:
            what = self._signalled.popleft()
            if what == "stop":
                self.stop()
            elif what == "reload":
                self._pending.append(("reload",))
            else:
                self._pending.append(("cmd", {"cmd": "recalibrate", "from": "SIGUSR1"}, None))

    # -- callbacks from other threads ---------------------------------------------------------
    def _on_control(self, msg: Any) -> None:
        # runs on the reader thread in stream order: ring.pushed is how many samples came before msg
        self.inbox.put(("msg", msg, self.ring.pushed, self.clock()))

    def _on_event(self, name: str, detail: str = "") -> None:
        self.inbox.put(("event", name, detail))

    def _on_command(self, request: dict[str, Any]) -> dict[str, Any]:
        if request.get("cmd") == "status":
            return {"ok": True, **self.status}
        reply = Reply()
        self.inbox.put(("cmd", request, reply))
        if not reply.event.wait(10.0):
            return {"ok": False, "error": "the engine loop did not answer within 10 s"}
        return reply.value

    # -- the loop -----------------------------------------------------------------------------
    def run(self, until: Any = None, timeout_s: float | None = None) -> None:
        """Run the loop until stop(), ``until(engine)`` is true, or ``timeout_s`` passes."""
        interval = self.notifier.watchdog_interval_s() if self.cfg.watchdog else None
        next_ping = 0.0
        deadline = None if timeout_s is None else self.clock() + timeout_s
        while True:
            self._take_signals()
            if self._stop.is_set():
                break
            now = self.clock()
            n = 0
            for _ in range(8):  # samples and messages in stream order, a bounded amount per round
                got, more = self._step(now)
                n += got
                if not more:
                    break
            self._contain("tick", self._tick, now)
            if now >= self._next_publish:
                self._contain("status", self._publish, now)
                self._next_publish = now + 0.2
            if interval is not None and now >= next_ping:
                self.notifier.watchdog()
                next_ping = now + interval
            if until is not None and until(self):
                break
            if deadline is not None and now > deadline:
                break
            if n < 64 and self.idle_sleep_s > 0:
                # a plain sleep, not a blocking inbox.get, so that a signal's work waits at most
                # one idle sleep (the handlers never touch the inbox; see install_signals)
                time.sleep(self.idle_sleep_s)

    def _contain(self, where: str, fn: Any, *args: Any) -> Any:
        """Run one handler; an exception is logged (once per kind, then every 1000th) and counted."""
        try:
            return fn(*args)
        except Exception as err:
            self.loop_errors += 1
            key = f"{where}:{type(err).__name__}"
            k = self._error_counts[key] = self._error_counts.get(key, 0) + 1
            if k == 1 or k % 1000 == 0:
                log.error("%s failed (%d time(s)); the daemon carries on: %s", where, k, err,
                          exc_info=k == 1)
            return None

    def _tick(self, now: float) -> None:
        self._retry_lock(now)
        if now >= self._next_errors_check:
            self._next_errors_check = now + self.ERRORS_SAY_S
            self._contain("link error summary", self._say_link_errors)
        if self.temp_check.dropped > self._temp_said[1]:  # drops within the last minute: said when it ends
            self._say_temperature(None, now)
        if self.session is not None:
            self.session.tick(now)
            if self.session.unconfirmed is not None and now >= self._next_hello_request:
                self._ask_hello(now)  # every 2 s, as before the first HELLO
        elif now >= self._next_hello_request and self.ring.pushed:
            self._ask_hello(now)

    TEMP_BLIND_SAY_S = 2.0
    """Seconds [s] of samples all dropped for their temperature before status names it as the reason."""

    OPEN_GARBAGE_BYTES = 64
    """Garbage bytes [bytes] a (re)opened link may drop at its start (a frame cut midway) unsaid."""

    def _say_link_errors(self) -> None:
        """One line per ERRORS_SAY_S [s] when the link dropped anything since the last: what it counted
        (CRC failures, bad lengths, implausible samples...). Every rejection was counted and never
        believed, but the log said nothing of 5000 garbage frames (an integrator's fault campaign)."""
        if self.link is None:
            return
        errors = {k: int(v) for k, v in (self.link.stats().get("errors") or {}).items()
                  if k in REJECTIONS and isinstance(v, int | float)}
        grown = {k: v - self._errors_said.get(k, 0) for k, v in errors.items()
                 if v > self._errors_said.get(k, 0)}
        self._errors_said = errors
        ups, self._ups_since_said = self._ups_since_said, 0
        if set(grown) == {"garbage_bytes"} and grown["garbage_bytes"] <= self.OPEN_GARBAGE_BYTES * ups:
            # the tail of a frame cut by the port's opening, at every start and reconnect: expected,
            # not a WARNING (an operator's audit: 25 of 25 restarts said it)
            log.debug("link %s: %d bytes of a frame cut by the port's opening dropped", self.link.target,
                      grown["garbage_bytes"])
            return
        if grown:
            log.warning("link %s: in the last %.0f s it dropped %s (counted in status link.errors, never "
                        "believed)", self.link.target, self.ERRORS_SAY_S,
                        ", ".join(f"{k} +{v}" for k, v in sorted(grown.items())))

    def _step(self, now: float) -> tuple[int, bool]:
        """Pop samples up to the next unit message's place in the stream, then handle the messages
        that are due. Returns (samples handled, whether there may be more to do now)."""
        while True:
            try:
                self._pending.append(self.inbox.get_nowait())
            except queue.Empty:
                break
        limit = 8192
        for item in self._pending:
            if item[0] == "msg":  # samples before it first (0.5 s at most: a lost sample never comes)
                if now - item[3] < 0.5:
                    limit = max(0, min(limit, item[2] - self.ring.position))
                break
        block = self.ring.pop(limit)
        if block.size:
            self._seq_hist.append((self.ring.position - block.size, block["seq"].copy()))
            self._contain("samples", self._on_samples, block, now)
        handled = self._drain(now)
        return block.size, bool(block.size >= limit > 0 or handled)

    def _seq_at(self, index: int) -> int | None:
        """The seq of the sample with this ring index (counted from the engine's start), if recent."""
        for start, seq in reversed(self._seq_hist):
            if start <= index < start + seq.size:
                return int(seq[index - start])
        return None

    def _drain(self, now: float) -> bool:
        """Handle pending items in order; a unit message waits (0.5 s at most) until the samples that
        came before it on the wire are popped, and every later item waits behind it."""
        handled = False
        while self._pending:
            item = self._pending[0]
            kind = item[0]
            if kind == "msg":
                _, msg, before, first_seen = item
                if before > self.ring.position and now - first_seen < 0.5:
                    return handled
                last_seq = self._seq_at(before - 1) if before > 0 else None
                self._contain(f"message {type(msg).__name__}", self._on_message, msg, now, last_seq)
            elif kind == "event":
                self._contain(f"link event {item[1]}", self._on_link_event, item[1], item[2], now)
            elif kind == "cmd":
                value = self._contain(f"command {item[1].get('cmd')!r}", self._command, item[1], now)
                if value is None:
                    value = {"ok": False, "error": "the command failed inside the daemon; see its log"}
                if item[2] is not None:
                    item[2].value = value
                    item[2].event.set()
            elif kind == "reload":
                self._contain("reload", self._reload)
            self._pending.pop(0)
            handled = True
        return handled

    def _ask_hello(self, now: float) -> None:
        """Ask the unit to announce itself (HELLO_REQUEST): it switched on before we listened."""
        self._next_hello_request = now + 2.0
        self._hello_asks += 1
        try:
            self.link.send(HelloRequest())
        except Exception as err:  # the link may be down; the reader thread reconnects
            log.debug("HELLO_REQUEST not sent: %s", err)

    def _on_message(self, msg: Any, now: float, last_seq: int | None = None) -> None:
        """A message from the unit; ``last_seq`` is the seq of the sample just before it on the wire."""
        if isinstance(msg, Hello):
            self._hello_asks = 0
            s = self.session
            if s is not None and (s.hello.serial, s.hello.boot_count) == (msg.serial, msg.boot_count):
                # an answer to a HELLO_REQUEST, or the switch-on HELLO still in the port's buffer
                log.debug("HELLO from unit %d again (boot %d): same switch-on, session continues",
                          msg.serial, msg.boot_count)
                if s.unconfirmed is not None:
                    log.info("HELLO from unit %d (boot %d) confirms who restarted its samples: same session",
                             msg.serial, msg.boot_count)
                    s.unconfirmed = None
                return
            self.last_hello = msg
            if (s is not None and s.hello.serial == msg.serial and self._seq_session_at is not None
                    and now - self._seq_session_at < ADOPT_WINDOW_S and msg.rate_hz
                    and abs(msg.rate_hz - s.rate_hz) > self.RATE_TOL * msg.rate_hz):
                # the session the sample sequence started was sized for the last boot's rate: kept, its
                # still detector never saw a still stretch at the new one (a unit rebooted from 800 to
                # 200 Hz was never calibrated: an audit with a unit built from protocol.md alone)
                log.info("HELLO from unit %d (boot %d) confirms the restart seen in the samples, at %g Hz: "
                         "the session started from the samples was sized for %g Hz; it starts again at "
                         "the stated rate", msg.serial, msg.boot_count, msg.rate_hz, s.rate_hz)
                self._seq_session_at = None
                self._start_session(msg, now, from_hello=True)
                return
            if (s is not None and s.hello.serial == msg.serial and self._seq_session_at is not None
                    and now - self._seq_session_at < ADOPT_WINDOW_S):
                # the sample sequence already showed this restart and started its session
                log.info("HELLO from unit %d (boot %d) confirms the restart seen in the samples: "
                         "same session",
                         msg.serial, msg.boot_count)
                s.hello = msg
                s.unconfirmed = None
                self._seq_session_at = None
                return
            log.info("HELLO from unit %d (firmware %s, boot %d): new session",
                     msg.serial, msg.fw_version, msg.boot_count)
            self._start_session(msg, now, from_hello=True)
            held = self.seq.expect_restart()  # the next jump in the numbering is this switch-on's
            if held is not None:
                self._feed(held, now)
            return
        if self.session is not None:
            self.session.on_message(msg, now, last_seq)

    FLAP_WINDOW_S = 60.0
    FLAP_SAY = 3
    """More link losses than this in FLAP_WINDOW_S [s]: one WARNING a minute, the rest at DEBUG."""

    def _flapping(self, now: float) -> bool:
        """More than FLAP_SAY link losses in the last FLAP_WINDOW_S [s]: a loose connector."""
        while self._flaps and now - self._flaps[0] > self.FLAP_WINDOW_S:
            self._flaps.popleft()
        return len(self._flaps) > self.FLAP_SAY

    def _on_link_event(self, name: str, detail: str, now: float) -> None:
        if name == "reconnecting":  # every back-off round: one line when the state or its cause changes
            why = _COUNTS.sub("#", detail.split("; next try in")[0])
            first = self._link_state != "reconnecting" or why != self._reconnect_why
            # a cause that changes is said too: after a replug, a second daemon held the port, and the
            # service's last line was still the unplug's "No such file" (a serial integrator's re-check);
            # while the link flaps, the minute's summary says it (20 WARNINGs a minute: an operator's audit)
            # the first round after a loss the engine has just said (WARNING) is its detail, at INFO:
            # one cable pull gave "link_lost" and "cannot be opened" as two WARNINGs (an integrator's
            # fault campaign, F3); a cause that changes later is a new fact
            level = logging.DEBUG if not first or self._flapping(now) else \
                logging.INFO if self._link_state == "link_lost" else logging.WARNING
            log.log(level, "waiting for the unit: %s", detail)
            self._link_state, self._reconnect_why = name, why
            self._reconnect_detail = detail.split("; ")[0]  # the cause, without the fix the log gives
            return
        self._reconnect_detail = None
        level = logging.INFO if name == "link_up" else logging.WARNING
        if name == "link_lost":
            self._flaps.append(now)
        if name in ("link_lost", "link_up") and self._flapping(now):
            # a loose connector: 5-10 lines and 1-3 WARNINGs per flap, 58k WARNINGs a day at one flap
            # every 1.5 s (an operator's audit). One WARNING a minute sums it up; each flap at DEBUG
            level = logging.DEBUG
            if now - self._flap_said_at >= self.FLAP_WINDOW_S:
                self._flap_said_at = now
                log.warning("link %s: lost %d times in the last %.0f s (a loose connector?); each loss and "
                            "return is logged at DEBUG until it settles", detail, len(self._flaps),
                            self.FLAP_WINDOW_S)
        log.log(level, "link %s %s", name, detail)
        self._link_state = name
        if name == "link_lost" and self.session is not None:
            self.session.link_lost()
        if name == "link_up":
            self._link_up_at = now
            self._ups_since_said += 1
            # the unit may have kept running or rebooted: ask who it is (a new boot count starts a
            # new session) and re-read the set it holds
            self._ask_hello(now)
            if self.session is not None:
                self.session.relink(now)

    def _start_session(self, hello: Hello, now: float, from_hello: bool = False,
                       resized: bool = False) -> None:
        """A new session for ``hello``'s unit; ``from_hello``: the unit itself said who it is (a
        restart seen only in the samples reuses the last HELLO, whose boot counter proves nothing);
        ``resized``: the same switch-on, sized again for its measured rate (_check_rate)."""
        if not resized:
            self.temp_check.reset()  # the unit may have cooled or warmed since the last switch-on
            self.sensor_check.reset()
        if not resized and not getattr(hello, "rate_hz", 0):
            # a switch-on that states no rate is sized from its own samples: the last boot's rate is only
            # the first guess, and its intervals must not outvote this boot's
            self._rate_dts.clear()
        self._session_from_hello = from_hello
        old = self.session
        if old is not None:
            old.close(f"a new session started (boot {hello.boot_count})", now)
        self._prune_store(hello.serial)  # bounded for years of switch-ons
        prior = self.store.held_last(hello.serial)  # what the unit held last, a rollback included
        caps = of_link(self.link)  # what this unit holds, as of its HELLO
        moved = frame_changed(caps, prior)
        if moved:  # a remounted autopilot: its stored set is in another body frame (capabilities.py)
            log.warning("unit %d: %s; starting cold", hello.serial, moved)
            prior = None
        rate = float(hello.rate_hz) if getattr(hello, "rate_hz", 0) else (self.rate_hz or 1000.0)
        learner = make_learner(self.cfg, prior, rate)
        self.detector = self._new_detector(rate)
        self._seq_session_at = None
        self.session = Session(self.cfg, hello, learner, self.store, self.link.send, now, rate,
                               warm_started_from=None if prior is None else prior.version,
                               caps=caps, same_boot=same_boot(prior, hello) if from_hello else None)
        if not resized:  # the same switch-on sized again for its measured rate is no new session (a
            self.sessions_started += 1  # HELLO stating rate 0 counted two: a serial integrator's audit)
        if old is not None:  # push results the store could not take yet: carried over, not lost
            self.session.unrecorded.extend(old.unrecorded)
            if old.unrecorded and self.session.store_error is None:
                # the store is as unavailable as it was: status said "ok" for 2 s at each new session
                # while the disk was still full (an operator's soak)
                self.session.store_error = old.store_error
        if prior is not None:
            log.info("unit %d: warm start from stored v%d", hello.serial, prior.version)
            last_boot = ((prior.push.get("unit") or {}).get("boot_count")
                         or (prior.session or {}).get("boot_count"))
            if from_hello and isinstance(last_boot, int) and 0 < hello.boot_count < last_boot:
                # protocol.md: +1 per switch-on, kept in flash. Going back, it is another unit with the
                # same serial, or this one's flash was reset: said, as the learning cannot tell (an
                # operator's soak opened a stale pty of another unit 4242 at boot 1 after boot 5, silently)
                log.warning("unit %d: its boot counter went back from %d (v%d) to %d: its flash was reset, "
                            "or this is another unit with the same serial", hello.serial, last_boot,
                            prior.version, hello.boot_count)

    def _on_samples(self, block: np.ndarray, now: float) -> None:
        finite = np.isfinite(block["t"])
        for f in ("wx", "wy", "wz", "ax", "ay", "az", "temp"):
            finite &= np.isfinite(block[f])
        if not finite.all():
            self.dropped_nonfinite += int((~finite).sum())
            block = block[finite]
            if block.size == 0:
                return
        # beyond what the wire carries (a replayed CSV's 1e300 deg/s changed its first push: rc36b M4)
        inside = within_range(block)
        if not inside.all():
            self.dropped_out_of_range += int((~inside).sum())
            block = block[inside]
            if block.size == 0:
                return
        # the unit speaks, whatever its temperature sensor reads: a dead one made it "silent"
        self._last_sample_at = now
        if self._silent:
            self._silent = False
            log.info("unit samples again after a silence")
        believable = self.temp_check.keep(block["t"], block["temp"])
        if not believable.all():
            self._say_temperature(block["temp"][~believable], now)
            self._temp_last_dropped_c = float(block["temp"][~believable][-1])
            block = block[believable]
            if block.size == 0:
                if self._temp_blind_since is None:
                    self._temp_blind_since = now
                return
        self._temp_blind_since = None
        for kind, part in self.seq.feed(block):
            if kind == "restart" and self.last_hello is not None:
                log.warning("sample sequence went back to %d for %d samples in a row: the unit restarted; "
                            "asking it who it is (HELLO_REQUEST), nothing is pushed until it answers",
                            int(part["seq"][0]), part.size)
                self._start_session(self.last_hello, now)
                self._seq_session_at = now
                # another unit may have been plugged in: until a HELLO names it, the session learns
                # but stores and pushes nothing under the last unit's serial
                self.session.unconfirmed = (
                    f"the sample sequence restarted without a HELLO: waiting for the unit to say who it "
                    f"is (HELLO_REQUEST sent); learning meanwhile, as unit {self.last_hello.serial} "
                    "until it answers, but pushing nothing")
                self._ask_hello(now)
            self._feed(part, now)

    def _say_temperature(self, dropped_c: np.ndarray | None, now: float) -> None:
        """One WARNING a minute at most for temperatures no sensor reads, with the counts so far; drops
        within a minute of the last word are said when that minute ends (a 1 s sensor outage 40 s after
        the first word went unsaid for good: an integrator's CAN campaign)."""
        said_at, said_n = self._temp_said
        if now - said_at >= 60.0:
            tc = self.temp_check
            last = "" if dropped_c is None else f"; this one {float(dropped_c[0]):.2f} degC"
            log.warning("unit temperature: %d samples dropped since the last word (%d out of %g..%g degC, "
                        "%d spikes in all%s): a sensor or firmware fault, never learnt",
                        tc.dropped - said_n, tc.out_of_range, TEMP_MIN_C, TEMP_MAX_C, tc.spikes, last)
            self._temp_said = (now, tc.dropped)

    def _feed(self, block: np.ndarray, now: float) -> None:
        self._measure_rate(block)
        self._check_rate(now)
        if self.session is None:
            self.samples_before_hello += block.size
            return
        if block.size:
            self.session.heard(float(block["t"][-1]))
        decided, still = self.detector.feed(block)
        still = self.sensor_check.judge(decided, still, self.detector, now)
        self.session.feed(decided, still, now)
        if decided.size:
            self._record_latency(self.clock() - decided["rx"])

    RATE_WINDOW = 256
    """Sample intervals [s] the measured rate is the median of: consecutive seq only, across blocks
    (a CAN link hands the engine one or two samples at a time)."""
    RATE_SETTLE = 64
    """Intervals measured since a switch-on before its measured rate may re-size the session."""
    RATE_TOL = 0.05
    """A session sized for a rate this far (relative) from the one that applies is sized again."""

    def _measure_rate(self, block: np.ndarray) -> None:
        """``rate_hz`` [Hz] from the samples' own time stamps (the unit's clock), for status and for a
        unit whose HELLO does not state its rate."""
        seq = block["seq"].astype(np.int64)
        t = block["t"].astype(np.float64)
        if self._rate_last is not None:
            seq, t = np.r_[self._rate_last[0], seq], np.r_[self._rate_last[1], t]
        self._rate_last = (int(seq[-1]), float(t[-1]))
        dt = np.diff(t)[(np.diff(seq) % SEQ_MODULO) == 1]
        self._rate_dts.extend(dt[dt > 0][-self.RATE_WINDOW:].tolist())
        if len(self._rate_dts) >= 8:
            self.rate_hz = round(1.0 / float(np.median(self._rate_dts)), 3)

    def _check_rate(self, now: float) -> None:
        """A unit whose HELLO states no rate (0) is sized from the rate measured from its samples'
        time stamps, as protocol.md says; at its HELLO that rate is not known yet (the guess is the last
        rate measured, else 1000 Hz), so once RATE_SETTLE intervals of this switch-on are measured, a
        session sized more than RATE_TOL away starts again at the measured rate, with one line.

        Why: sized for 1000 Hz, a 200 Hz unit's still detector wanted a still stretch five times as
        long as the one it had, and the unit was never calibrated (an audit with a unit built from
        protocol.md alone: 0 still samples after 268 s)."""
        s = self.session
        if (s is None or s.hello.rate_hz or self.rate_hz is None or len(self._rate_dts) < self.RATE_SETTLE
                or abs(self.rate_hz - s.rate_hz) <= self.RATE_TOL * self.rate_hz):
            return
        log.warning("unit %d: its HELLO states no rate; this switch-on was sized for %g Hz, but its samples "
                    "come at %g Hz: the session starts again at that rate", s.hello.serial, s.rate_hz,
                    self.rate_hz)
        unconfirmed, from_hello = s.unconfirmed, self._session_from_hello
        self._start_session(s.hello, now, from_hello=from_hello, resized=True)
        if unconfirmed is not None and self.session is not None:
            self.session.unconfirmed = unconfirmed

    def _record_latency(self, lat_s: np.ndarray) -> None:
        """Keep the newest latencies: from a sample's arrival (rx) to the weights having learnt it."""
        lat = lat_s[-self._lat.size:]
        idx = (self._lat_i + np.arange(lat.size)) % self._lat.size
        self._lat[idx] = lat
        self._lat_i = int((self._lat_i + lat.size) % self._lat.size)

    def latency_percentiles_s(self) -> dict[str, float]:
        """p50 / p99 / max of the sample-to-weights latency [s] over the newest 16384 samples."""
        v = self._lat[np.isfinite(self._lat)]
        if v.size == 0:
            return {}
        p50, p99 = np.percentile(v, [50, 99])
        return {"p50": float(p50), "p99": float(p99), "max": float(v.max()), "n": int(v.size)}

    # -- status -------------------------------------------------------------------------------
    def _store_view(self, serial: int) -> dict[str, Any]:
        """What the store says about this unit: its newest set the unit verifiably held, and pushes
        that have not ended (beside the session's ``unit_set``: what the unit holds, and whether the
        two agree)."""
        try:
            recs = self.store.history(serial)
        except Exception as err:
            return {"error": str(err)}
        held = self.store.held_last(serial)  # after a rollback to v1, v1 (not the highest applied)
        return {"versions": len(recs), "latest_applied": None if held is None else held.version,
                "pending": [r.version for r in recs if r.push.get("status") == "pending"],
                "read_only_at_start": self.store.read_only}

    def _publish(self, now: float) -> None:
        link_stats = self.link.stats() if self.link is not None else {}
        ring = {"pushed": self.ring.pushed, "popped": self.ring.popped, "lost": self.ring.lost}
        connected = bool(link_stats.get("connected"))
        age = None if self._last_sample_at is None else now - self._last_sample_at
        if self.session is None:
            if not link_stats.get("frames"):
                waiting = "waiting for the unit's HELLO: no frame received yet"
            elif self._hello_asks < self.HELLO_ASKS_BEFORE_ADVICE:
                waiting = (f"waiting for the unit's HELLO: {self.samples_before_hello} samples received "
                           f"without one; asked for it (HELLO_REQUEST sent {self._hello_asks} time(s))")
            else:
                waiting = (f"waiting for the unit's HELLO: {self.samples_before_hello} samples received "
                           f"without one and {self._hello_asks} HELLO_REQUESTs unanswered; power-cycle "
                           "the unit or check its firmware")
            if link_stats.get("fault"):
                # an autopilot link that cannot say HELLO says why (the wrong autopilot type, a board
                # rotation it cannot use); the HELLO count alone hid it (an integrator's audit)
                waiting = f"waiting for the unit's HELLO: the link reports a fault: {link_stats['fault']}"
            status = {"state": "WAIT_HELLO", "reason": waiting}
        else:
            status = self.session.status()
            status["store_view"] = self._store_view(self.session.hello.serial)
            status["still"] = self.detector.status()
            if not status.get("trained_samples") and status["still"].get("why"):
                status["reason"] = f"{status['reason']}; {status['still']['why']}"  # why nothing is learnt
            status["sensor"] = self.sensor_check.status(self.detector.core.flat_rows)
            blind = self._temp_blind_since
            if blind is not None and now - blind >= self.TEMP_BLIND_SAY_S:
                # every sample dropped for its temperature: the reason blamed "learning the unit's noise
                # level (0 of 200 samples)" (an integrator's campaign, rc36a S4)
                status["sensor"]["fault"] = (
                    f"every sample's temperature is dropped for {now - blind:.0f} s (the last "
                    f"{self._temp_last_dropped_c:.2f} degC; -327.68 is the sensor's 'no reading'; outside "
                    f"{TEMP_MIN_C:g}..{TEMP_MAX_C:g} degC or a spike): nothing is learnt until it reads")
            if status["sensor"]["fault"]:
                status["reason"] = f"the unit's sensors report garbage: {status['sensor']['fault']}; " \
                                   f"{status['reason']}"
        # silent: connected and no sample for SILENT_AFTER_S of the connection (the age of the last
        # sample before an outage made a link just back "silent for 6 s": an operator's soak)
        up_for = now - self._link_up_at if self._link_up_at is not None else None
        silent = (connected and age is not None and age > SILENT_AFTER_S
                  and (up_for is None or up_for > SILENT_AFTER_S)
                  # samples in the ring not read yet: the unit speaks, this loop was held up (a store
                  # write of 12 s on a slow disk made a healthy unit "silent": an operator's re-check)
                  and len(self.ring) == 0)
        if silent and getattr(self.link, "holds_samples_in_push", False) and self.session is not None \
                and self.session.push is not None and not self.session.push.finished:
            # an autopilot's link withholds the samples while it rewrites the compensation (they would
            # mix two sets); it hears the autopilot, and a silent one fails the push (heartbeat lost)
            silent = False
        if not connected and isinstance(status.get("unit_set"), dict) and status["unit_set"].get("note"):
            # what the unit held when it was last read: while the link is down another host may write
            # it (a second daemon that took the port pushed its own v2, and status still said "holds
            # v1, as the store says": a serial integrator's re-check)
            status["unit_set"] = {**status["unit_set"], "note": status["unit_set"]["note"]
                                  + " (when last read: the link is down now)", "stale": True}
        if not connected or (age is None and self.session is None and not link_stats.get("frames")):
            status["session_state"] = status["state"]
            status["state"] = "WAIT_UNIT"
            status["reason"] = (f"waiting for the unit: link to {link_stats.get('target', '?')} is down"
                                + (f" ({self._reconnect_detail})" if self._reconnect_detail else "")
                                if not connected else
                                f"waiting for the unit: {link_stats.get('target', '?')} is open, "
                                "nothing heard yet")
            foreign = int((link_stats.get("errors") or {}).get("foreign_frames") or 0)
            if connected and foreign:
                # frames of other nodes on the bus, none of this one's: the node id is the usual cause
                # (a node-0 daemon on a node-5 unit's bus said only "nothing heard yet": an audit)
                status["reason"] += (f"; {foreign} frames of other CAN nodes seen, none of this node's: "
                                     "check link.can_node_id against the unit's (docs/protocol.md, "
                                     "section 3, \"Setting the node id\")")
        elif silent:
            status["session_state"] = status["state"]
            status["state"] = "UNIT_SILENT"
            status["reason"] = (f"unit silent: no sample for {age:.0f} s" if age is not None
                                else "unit silent: connected, but no sample yet")
        elif self.session is not None and link_stats.get("hold"):  # an autopilot's own calibration run
            status["reason"] = f"{link_stats['hold']}; {status.get('reason', '')}"
        elif self.session is not None and (link_stats.get("fault") or link_stats.get("read_fault")):
            # a fault the link found after the HELLO (an autopilot whose IMU gives no temperature, one
            # that stopped answering parameter reads): the session's own reason ("only 0 of 500
            # samples") hid it (an integrator's audit)
            fault = link_stats.get("fault") or link_stats.get("read_fault")
            status["reason"] = f"the link reports a fault: {fault}; {status.get('reason', '')}"
        if silent != self._silent:
            if silent:
                log.warning("%s", status["reason"])
            self._silent = silent
        status.update({"pid": os.getpid(), "uptime_s": round(now - self.started, 1), "link": link_stats,
                       "ring": ring, "dropped_nonfinite": self.dropped_nonfinite,
                       "dropped_out_of_range": self.dropped_out_of_range,
                       "dropped_temperature": {"out_of_range": self.temp_check.out_of_range,
                                               "spikes": self.temp_check.spikes},
                       "liveness": {"sample_age_s": None if age is None else round(age, 3),
                                    "silent": silent, "silent_after_s": SILENT_AFTER_S},
                       "sequence": {"outliers": self.seq.outliers, "restarts": self.seq.restarts,
                                    "gaps": self.seq.gaps, "held": self.seq.pending},
                       "loop_errors": self.loop_errors, "reload": self.last_reload,
                       "sessions": self.sessions_started, "config": self.cfg.source,
                       "rate_hz": self.rate_hz, "latency_s": self.latency_percentiles_s()})
        if self.last_reload is not None and not self.last_reload["ok"]:
            # systemd's STATUS= said nothing of it, `systemctl reload` exits 0, and the file that would
            # fail the next start stayed on disk (an operator's audit)
            status["reason"] = (f"{status.get('reason', '')}; the config on disk was refused at the last "
                                f"reload ({self.last_reload['error']}): the running config stays, and the "
                                "next start fails until the file is fixed")
        self.status = status
        line = f"{status['state']}: {status.get('reason', '')}"
        if line != self._last_status_line:
            self._last_status_line = line
            self.notifier.status(line)
            # the journal gets a line when the state or the kind of reason changes, not at every
            # count in it ("only 215 of 800 samples", "rank 3 < 9"): systemd's STATUS= has every one
            kind = _COUNTS.sub("#", line)
            if kind != self._last_logged_kind:
                self._last_logged_kind = kind
                # a flapping link's WAIT_UNIT and back, every flap: the minute's summary says it
                log.log(logging.DEBUG if self._flapping(now) else logging.INFO, "%s", line)
