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
"""

from __future__ import annotations

import logging
import os
import queue
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gyrocal.daemon.config import DaemonConfig, load_config
from gyrocal.daemon.control import ControlServer
from gyrocal.daemon.learner import make_learner
from gyrocal.daemon.notify import Notifier
from gyrocal.daemon.ring import RingBuffer
from gyrocal.daemon.session import Session, State
from gyrocal.daemon.stillness import RETIRED_FIELDS, StillDetector
from gyrocal.daemon.store import CalibrationRecord, CalibrationStore
from gyrocal.drivers import open_link
from gyrocal.protocol.messages import Hello, HelloRequest

log = logging.getLogger("gyrocal.engine")


@dataclass
class Reply:
    """A reply slot for a control command handed to the engine loop."""

    event: threading.Event = field(default_factory=threading.Event)
    value: dict[str, Any] = field(default_factory=dict)


class Engine:
    """Joins one link to sessions, the store, the control socket and systemd."""

    def __init__(self, cfg: DaemonConfig, link_cfg: dict[str, Any] | None = None) -> None:
        self.cfg = cfg
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
        self.rate_hz: float | None = None
        self.status: dict[str, Any] = {"state": "STARTING"}
        self.started = time.monotonic()
        self.dropped_nonfinite = 0
        self.samples_before_hello = 0
        self.sessions_started = 0
        self.push_results: list[dict[str, Any]] = []
        self._stop = threading.Event()
        self._last_seq: int | None = None
        self._last_status_line = ""
        self._next_hello_request = 0.0
        self._next_publish = 0.0
        self._popped_total = 0  # samples popped from the ring since start (the ring's own count)
        self._seq_hist: deque[tuple[int, np.ndarray]] = deque(maxlen=8)
        self._held: list[tuple[Any, ...]] = []  # unit messages waiting for their preceding samples
        # sample-to-weights latency [s]: a fixed-size reservoir of the newest values (O(1) memory)
        self._lat = np.full(1 << 14, np.nan)
        self._lat_i = 0

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
        backoff = {"backoff_max_s": float(c.get("reconnect_max_s", 5.0))}
        if c["kind"] == "can":
            return {"kind": "can", "bus": dict(c["can"]), "node_id": int(c.get("can_node_id", 0)), **backoff}
        return {"kind": "serial", "url": c["url"], "baudrate": int(c.get("baudrate", 921600)), **backoff}

    def open(self, wait: bool = True) -> None:
        """Open the link (``wait=False``: keep retrying in the background if the device is absent)."""
        self.link = open_link(self._driver_cfg(), self.ring, self._on_control, self._on_event,
                              where=f"{self.cfg.source}: link", start=False)
        self.link.start(wait=wait)
        self._ask_hello(time.monotonic())
        self.control = ControlServer(self.cfg.control_socket, self._on_command)
        self.control.start()
        log.info("control socket %s; state directory %s", self.cfg.control_socket, self.cfg.state_dir)
        self.notifier.ready()
        self.notifier.status("waiting for the unit's HELLO")

    def close(self) -> None:
        self.notifier.stopping()
        if self.control is not None:
            self.control.stop()
        if self.link is not None:
            self.link.stop()
        log.info("stopped")

    def stop(self) -> None:
        self._stop.set()

    def install_signals(self) -> None:
        signal.signal(signal.SIGTERM, lambda *_: self.stop())
        signal.signal(signal.SIGINT, lambda *_: self.stop())
        signal.signal(signal.SIGHUP, lambda *_: self.inbox.put(("reload",)))
        signal.signal(signal.SIGUSR1, lambda *_: self.inbox.put(("cmd", {"cmd": "recalibrate"}, None)))

    # -- callbacks from other threads ---------------------------------------------------------
    def _on_control(self, msg: Any) -> None:
        # runs on the reader thread in stream order: ring.pushed is how many samples came before msg
        self.inbox.put(("msg", msg, self.ring.pushed))

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
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._stop.is_set():
            now = time.monotonic()
            block = self.ring.pop(8192)
            if block.size:
                self._seq_hist.append((self._popped_total, block["seq"].copy()))
                self._popped_total += block.size
                self._on_samples(block, now)
            self._drain_inbox(now)
            if self.session is not None:
                self.session.tick(now)
            elif now >= self._next_hello_request and self.ring.pushed:
                self._ask_hello(now)
            if now >= self._next_publish:
                self._publish(now)
                self._next_publish = now + 0.2
            if interval is not None and now >= next_ping:
                self.notifier.watchdog()
                next_ping = now + interval
            if until is not None and until(self):
                break
            if deadline is not None and now > deadline:
                break
            if block.size < 64:
                time.sleep(0.002)

    def _seq_at(self, index: int) -> int | None:
        """The seq of the sample with this ring index (counted from the engine's start), if recent."""
        for start, seq in reversed(self._seq_hist):
            if start <= index < start + seq.size:
                return int(seq[index - start])
        return None

    def _drain_inbox(self, now: float) -> None:
        """Handle what the other threads posted; a unit message waits until the samples that came
        before it on the wire have been popped, so messages and samples are handled in stream order."""
        pending, self._held = self._held, []
        while True:
            if pending:
                item = pending.pop(0)  # held messages first, in their order
            else:
                try:
                    item = self.inbox.get_nowait()
                except queue.Empty:
                    return
            kind = item[0]
            if kind == "msg":
                _, msg, before, *seen = item
                first_seen = seen[0] if seen else now
                # hold it while the samples before it are in flight (0.5 s at most), and hold every
                # later message behind it, so the unit's messages keep their order
                if self._held or (before > self._popped_total and now - first_seen < 0.5):
                    self._held.append(("msg", msg, before, first_seen))
                    continue
                last_seq = self._seq_at(before - 1) if before > 0 else None
                self._on_message(msg, now, last_seq)
            elif kind == "event":
                self._on_link_event(item[1], item[2], now)
            elif kind == "cmd":
                value = self._command(item[1], now)
                if item[2] is not None:
                    item[2].value = value
                    item[2].event.set()
            elif kind == "reload":
                self._reload()

    def _ask_hello(self, now: float) -> None:
        """Ask the unit to announce itself (HELLO_REQUEST): it switched on before we listened."""
        self._next_hello_request = now + 2.0
        try:
            self.link.send(HelloRequest())
        except Exception as err:  # the link may be down; the reader thread reconnects
            log.debug("HELLO_REQUEST not sent: %s", err)

    def _on_message(self, msg: Any, now: float, last_seq: int | None = None) -> None:
        """A message from the unit; ``last_seq`` is the seq of the sample just before it on the wire."""
        if isinstance(msg, Hello):
            s = self.session
            if s is not None and (s.hello.serial, s.hello.boot_count) == (msg.serial, msg.boot_count):
                log.info("HELLO from unit %d again (boot %d): same switch-on, session continues",
                         msg.serial, msg.boot_count)
                return
            log.info("HELLO from unit %d (firmware %s, boot %d): switch-on, new session",
                     msg.serial, msg.fw_version, msg.boot_count)
            self.last_hello = msg
            self._start_session(msg, now)
            return
        if self.session is not None:
            self.session.on_message(msg, now, last_seq)

    def _on_link_event(self, name: str, detail: str, now: float) -> None:
        log.log(logging.INFO if name == "link_up" else logging.WARNING, "link %s %s", name, detail)
        if name == "link_up":
            # the unit may have kept running or rebooted: ask who it is (a new boot count starts a
            # new session) and re-read the set it holds
            self._ask_hello(now)
            if self.session is not None:
                self.session.applied = None
                self.session.request_read(now)

    def _start_session(self, hello: Hello, now: float) -> None:
        prior = self.store.latest(hello.serial, acked_only=True)
        rate = float(hello.rate_hz) if getattr(hello, "rate_hz", 0) else (self.rate_hz or 1000.0)
        learner = make_learner(self.cfg, prior, rate)
        self.detector = self._new_detector(rate)
        self.session = Session(self.cfg, hello, learner, self.store, self.link.send, now, rate,
                               warm_started_from=None if prior is None else prior.version)
        self.sessions_started += 1
        if prior is not None:
            log.info("unit %d: warm start from stored v%d", hello.serial, prior.version)

    def _on_samples(self, block: np.ndarray, now: float) -> None:
        fields = ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp")
        finite = np.all(np.column_stack([np.isfinite(block[f]) for f in fields]), axis=1)
        if not finite.all():
            self.dropped_nonfinite += int((~finite).sum())
            block = block[finite]
            if block.size == 0:
                return
        if block.size > 8:
            dt = np.median(np.diff(block["t"]))
            if dt > 0:
                self.rate_hz = 1.0 / dt
        seq = block["seq"].astype(np.int64)
        if self._last_seq is not None and seq[0] + 1000 < self._last_seq and self.last_hello is not None:
            log.warning("sample sequence went back (%d -> %d): the unit restarted", self._last_seq, seq[0])
            self._start_session(self.last_hello, now)
        self._last_seq = int(seq[-1])
        if self.session is None:
            self.samples_before_hello += block.size
            return
        decided, still = self.detector.feed(block)
        self.session.feed(decided, still, now)
        if decided.size:
            self._record_latency(time.monotonic() - decided["rx"])

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

    # -- commands -----------------------------------------------------------------------------
    def _command(self, req: dict[str, Any], now: float) -> dict[str, Any]:
        cmd = req.get("cmd")
        try:
            if cmd == "recalibrate":
                if self.last_hello is None:
                    return {"ok": False, "error": "no unit has announced itself (HELLO) yet"}
                self._start_session(self.last_hello, now)
                return {"ok": True, "message": "new calibration session started"}
            if cmd in ("rollback", "push"):
                return self._push_command(req, now)
        except Exception as err:  # a bad command must not stop the loop
            log.exception("command %r failed", cmd)
            return {"ok": False, "error": str(err)}
        return {"ok": False, "error": f"unknown command {cmd!r}; use status, recalibrate, rollback, push"}

    def _push_command(self, req: dict[str, Any], now: float) -> dict[str, Any]:
        s = self.session
        if s is None:
            return {"ok": False, "error": "no unit session yet; wait for the unit's HELLO"}
        if s.state is State.PUSHING:
            return {"ok": False, "error": "a push is already under way; try again in a few seconds"}
        serial = s.hello.serial
        if req["cmd"] == "rollback":
            target = req.get("to")
            history = [r for r in self.store.history(serial) if r.push.get("status") == "acked"]
            if target is None:
                current = s.applied.version if s.applied is not None else None
                older = [r for r in history if current is None or r.version < current]
                if not older:
                    return {"ok": False, "error": "no earlier acked calibration to roll back to"}
                rec = older[-1]
            else:
                rec = self.store.get(serial, int(target))
                if rec is None:
                    return {"ok": False, "error": f"unit {serial} has no calibration v{target}"}
            s.start_push(rec.version, list(rec.terms), np.asarray(rec.coefficients_dps), now)
            return {"ok": True, "message": f"pushing v{rec.version}", "version": rec.version}
        terms = [str(t) for t in req["terms"]]
        coeffs = np.asarray(req["coefficients"], dtype=np.float64)
        if coeffs.shape != (3, len(terms)) or not np.all(np.isfinite(coeffs)):
            return {"ok": False, "error": f"coefficients must be 3 finite rows of {len(terms)} numbers"}
        rec = self.store.add(CalibrationRecord(
            serial=serial, version=0, terms=terms, coefficients_dps=coeffs.tolist(),
            uncertainty_dps=[[float("nan")] * len(terms)] * 3, identifiable={}, stats={"source": "file"},
            session={"boot_count": s.hello.boot_count}, push={"status": "pending"}))
        s.start_push(rec.version, terms, coeffs, now)
        return {"ok": True, "message": f"pushing v{rec.version}", "version": rec.version}

    def _reload(self) -> None:
        self.notifier.reloading()
        if self.cfg.source.startswith("<"):
            log.info("SIGHUP: no config file to reload")
        else:
            try:
                new = load_config(self.cfg.source)
            except Exception as err:  # a broken edit must not kill a running daemon
                log.error("SIGHUP: config not reloaded: %s", err)
            else:
                if new.link != self.cfg.link:
                    log.warning("SIGHUP: link settings changed; they take effect at the next restart")
                for section in ("validation", "push", "monitor", "still", "estimator"):
                    setattr(self.cfg, section, getattr(new, section))
                log.info("SIGHUP: configuration reloaded from %s", self.cfg.source)
        self.notifier.ready()

    # -- status -------------------------------------------------------------------------------
    def _publish(self, now: float) -> None:
        link_stats = self.link.stats() if self.link is not None else {}
        ring = {"pushed": self.ring.pushed, "popped": self.ring.popped, "lost": self.ring.lost}
        if self.session is None:
            waiting = ("waiting for the unit's HELLO: no frame received yet" if not link_stats.get("frames")
                       else f"waiting for the unit's HELLO: {self.samples_before_hello} samples received "
                            "without one; power-cycle the unit or check its firmware")
            status = {"state": "WAIT_HELLO", "reason": waiting}
        else:
            status = self.session.status()
            status["still"] = self.detector.status()
            if not status.get("trained_samples") and status["still"].get("why"):
                status["reason"] = f"{status['reason']}; {status['still']['why']}"  # why nothing is learnt
        status.update({"pid": os.getpid(), "uptime_s": round(now - self.started, 1), "link": link_stats,
                       "ring": ring, "dropped_nonfinite": self.dropped_nonfinite,
                       "sessions": self.sessions_started, "config": self.cfg.source,
                       "rate_hz": self.rate_hz, "latency_s": self.latency_percentiles_s()})
        self.status = status
        line = f"{status['state']}: {status.get('reason', '')}"
        if line != self._last_status_line:
            self._last_status_line = line
            self.notifier.status(line)
            log.info("%s", line)
