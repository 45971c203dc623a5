"""The daemon's own Engine on a recording, off line, on the recording's clock.

``replay(recording, cfg)`` builds ``daemon.engine.Engine`` with a ``SimClock`` and a ReplayLink and
runs the engine's own loop (``Engine.run``): the same Session, still detector, learner, validation
and push transaction as on the vehicle. Between two rounds of the loop the link pumps the next
chunk of the recording and moves the clock to its unit time, so a 1 h log runs in seconds and every
run takes the same decisions (no wall-clock time enters them). The control socket and systemd are
not started: nobody can talk to a replay but its recording.

The result is a JSON-ready summary: sessions, validations, pushes (the coefficients the daemon
decided to push, recorded, not sent) and the decision log (each state change with its reason).
"""

from __future__ import annotations

import logging
import time
from typing import Any

from gyrocal.daemon.config import DaemonConfig
from gyrocal.daemon.engine import Engine
from gyrocal.daemon.session import Session
from gyrocal.replay.link import ReplayLink, SimClock
from gyrocal.replay.source import Recording

log = logging.getLogger("gyrocal.replay")

TAIL_S = 10.0
"""After the recording ends, simulated time allowed for a push or read under way to finish [s]."""
TAIL_STEP_S = 0.1
PUBLISH_S = 5.0
"""Status snapshots off line [s of recording]: only the summary reads them (live: every 0.2 s)."""


class Replay:
    """One off-line replay: ``run()`` then ``summary()``."""

    def __init__(self, recording: Recording, cfg: DaemonConfig, chunk_s: float = 1.0) -> None:
        self.recording = recording
        self.clock = SimClock()
        self.engine = Engine(cfg, clock=self.clock)
        self.engine.idle_sleep_s = 0.0  # the loop pumps the next chunk itself: never wait for one
        self.link = ReplayLink(recording, self.engine.ring, self.engine._on_control, self.engine._on_event,
                               clock=self.clock, chunk_s=chunk_s)
        self.engine.link = self.link
        publish, self._next_publish = self.engine._publish, 0.0

        def throttled(now: float) -> None:  # nobody polls a replay's status: save the engine's time
            if now >= self._next_publish:
                self._next_publish = now + PUBLISH_S
                publish(now)

        self.engine._publish = throttled  # type: ignore[method-assign]
        self.sessions: list[Session] = []
        self.decisions: list[dict[str, Any]] = []
        self.validations: list[dict[str, Any]] = []
        self._seen: tuple[Any, ...] = ()
        self._last_validation: dict[str, Any] | None = None
        self._tail = 0.0
        self.wall_s = 0.0

    def run(self) -> None:
        t0 = time.perf_counter()
        self.link.start()
        try:
            self.engine.run(until=self._step)
        finally:
            self.wall_s = time.perf_counter() - t0
            self.link.stop()

    def _step(self, engine: Engine) -> bool:
        """Called by the engine loop after each round: note decisions, then feed the next chunk."""
        self._note(engine)
        if self.link.pump():
            return False
        if len(engine.ring) or not engine.inbox.empty() or engine._pending:
            return False
        s = engine.session
        busy = s is not None and (s.push is not None or s.applied is None)
        if busy and self._tail < TAIL_S:
            self._tail += TAIL_STEP_S
            self.clock.now += TAIL_STEP_S
            return False
        self._note(engine)
        return True

    def _note(self, engine: Engine) -> None:
        s = engine.session
        if s is None:
            return
        if not self.sessions or self.sessions[-1] is not s:
            self.sessions.append(s)
        key = (len(self.sessions), s.state.value)
        if key != self._seen:  # a state change (reasons change with every sample count: not logged)
            self._seen = key
            self.decisions.append({"t_s": round(self.clock.now, 6), "session": len(self.sessions) - 1,
                                   "state": s.state.value, "reason": s.reason})
        if s.last_validation and s.last_validation is not self._last_validation:
            self._last_validation = s.last_validation
            self.validations.append({"t_s": round(self.clock.now, 6), "session": len(self.sessions) - 1,
                                     **s.last_validation})

    def summary(self) -> dict[str, Any]:
        eng, link = self.engine, self.link
        samples = int(link.stats()["samples"])
        sessions = []
        for i, s in enumerate(self.sessions):
            st = s.status()
            sessions.append({"index": i, "unit": st["unit"], "final_state": st["state"],
                             "reason": st["reason"],
                             "samples": st["samples"], "still_samples": st["still_samples"],
                             "trained_samples": st["trained_samples"], "converged": st["converged"],
                             "applied": st["applied"], "terms": st["terms"],
                             "last_push": {k: v for k, v in st["last_push"].items() if k != "utc"},
                             "coefficients_dps": st["coefficients_dps"],
                             "uncertainty_dps": st["uncertainty_dps"], "alarm": st["alarm"]})
        pushes = []
        results = [r for s in self.sessions for r in ([s.last_push] if s.last_push else [])]
        for p in link.unit.pushes:
            res = next((r for r in results if r.get("version") == p["version"]), {})
            pushes.append({**p, "engine_result": res.get("status"), "readback_ok": res.get("readback_ok")})
        duration = float(self.clock.now)
        return {
            "recording": self.recording.path, "format": self.recording.kind,
            # what the engine dropped too (out of range, temperatures no sensor reads): they were
            # missing from "dropped" (rc36b L4)
            "samples": samples, "dropped": {**self.recording.dropped(), **{k: v for k, v in (
                ("nonfinite", eng.dropped_nonfinite), ("out_of_range", eng.dropped_out_of_range),
                ("implausible_temperature", eng.temp_check.dropped)) if v}},
            "samples_before_hello": eng.samples_before_hello, "sessions_started": eng.sessions_started,
            "hello_synthesized": link.unit.synthesized_hello,
            "replayed_s": round(duration, 3), "wall_s": round(self.wall_s, 3),
            "samples_per_s": round(samples / self.wall_s, 1) if self.wall_s > 0 else None,
            "sessions": sessions, "validations": self.validations, "pushes": pushes,
            "decisions": self.decisions,
            # the recording's warnings (units, pauses, instances) in the JSON too, not on stderr only:
            # a log in m/s^2 was replayed into a "validated" push 57x too small (a foreign-log audit)
            "warnings": list(self.recording.warnings),
            # samples the still detector had not decided when its session ended (its look-ahead, a few
            # tenths of a second per session): the sessions' counts are short by these, nothing is lost
            "not_decided": max(0, samples - eng.samples_before_hello - eng.dropped_nonfinite
                               - eng.dropped_out_of_range - eng.temp_check.dropped
                               - sum(int(x["samples"]) for x in sessions)),
        }


def replay(recording: Recording, cfg: DaemonConfig, chunk_s: float = 1.0) -> dict[str, Any]:
    """Replay a recording through the daemon's engine; returns the summary (see Replay.summary)."""
    r = Replay(recording, cfg, chunk_s)
    r.run()
    return r.summary()


__all__ = ["Replay", "replay"]
