"""An in-process unit + session at any grade and rate: the daemon's logic without processes or links.

Time advances by the samples rendered (``now`` = unit time), so a run is deterministic for a seed and
independent of the machine's load. The unit answers the session's messages after the samples it has
rendered so far, as on the wire.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gyrocal.daemon.config import DaemonConfig, load_config
from gyrocal.daemon.learner import make_learner
from gyrocal.daemon.session import Session
from gyrocal.daemon.stillness import StillDetector
from gyrocal.daemon.store import CalibrationStore
from gyrocal.sim.grades import grade_truth
from gyrocal.sim.schedule import Schedule, tumble
from gyrocal.sim.truth import TruthModel
from gyrocal.sim.unit import VirtualUnit
from tests.daemon_harness import to_ring


@dataclass
class GradeRun:
    cfg: DaemonConfig
    unit: VirtualUnit
    store: CalibrationStore
    rate_hz: float
    session: Session | None = None
    detector: StillDetector | None = None
    now: float = 0.0
    hello_at: float = 0.0
    outbox: list[Any] = field(default_factory=list)
    pushes: list[dict[str, Any]] = field(default_factory=list)
    alarms: int = 0

    @classmethod
    def make(cls, tmp: Path, grade: str = "demo", rate_hz: float = 1000.0, seed: int = 1,
             truth: TruthModel | None = None, schedule: Schedule | None = None, **overrides: Any) -> GradeRun:
        cfg = load_config(None, {"state_dir": str(tmp / "state"), "control_socket": str(tmp / "c.sock"),
                                 **overrides})
        unit = VirtualUnit(truth or grade_truth(grade, rate_hz), schedule or tumble(1.2, 0.4), rate_hz,
                           seed, 4242)
        return cls(cfg, unit, CalibrationStore(cfg.state_dir), rate_hz)

    def send(self, msg: Any) -> None:
        last_seq = self.unit.session_index - 1 if self.unit.session_index else None
        self.outbox.extend((reply, last_seq) for reply in self.unit.handle(msg))

    def switch_on(self) -> None:
        hello = self.unit.power_on()
        prior = self.store.latest(hello[0].serial, acked_only=True)
        self.detector = StillDetector.for_rate(self.rate_hz, self.cfg.still)
        self.hello_at = self.now
        self.session = Session(self.cfg, hello[0], make_learner(self.cfg, prior, self.rate_hz), self.store,
                               self.send, self.now, self.rate_hz, None if prior is None else prior.version)

    def run(self, seconds: float, until: Any = None, step_s: float = 0.05) -> None:
        step = max(1, int(round(step_s * self.rate_hz)))
        for _ in range(int(seconds * self.rate_hz / step)):
            self.now += step / self.rate_hz
            block = to_ring(self.unit.render(step))
            s, d = self.session, self.detector
            assert s is not None and d is not None
            replies, self.outbox = self.outbox, []
            for msg, last_seq in replies:
                s.on_message(msg, self.now, last_seq)
            decided, still = d.feed(block)
            s.feed(decided, still, self.now)
            was = s.alarm
            s.tick(self.now)
            if s.alarm and not was:
                self.alarms += 1
            if s.last_push and (not self.pushes or self.pushes[-1]["push"] is not s.last_push):
                self.pushes.append({"t": self.now - self.hello_at, "push": s.last_push,
                                    "drift": self.unit.status()["drift_rms_compensated_dps"]})
            if until is not None and until(self):
                return


def first_push(r: GradeRun) -> bool:
    return bool(r.pushes)
