"""An in-process harness: a Session driven by a VirtualUnit, on the unit's own clock.

No threads, no sleeps: samples, replies and timeouts advance on simulated time, so the daemon's
state machine is tested deterministically. The real estimator, store and unit logic are used.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gyrocal.daemon.config import DaemonConfig, load_config
from gyrocal.daemon.learner import make_learner
from gyrocal.daemon.ring import SAMPLE_DTYPE
from gyrocal.daemon.session import Session
from gyrocal.daemon.stillness import StillDetector
from gyrocal.daemon.store import CalibrationStore
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import TruthModel
from gyrocal.sim.unit import Faults, VirtualUnit

RATE_HZ = 400.0


def to_ring(chunk: Any) -> np.ndarray:
    c = chunk.columns
    out = np.zeros(chunk.seq.size, dtype=SAMPLE_DTYPE)
    out["seq"] = chunk.seq
    for k in ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp"):
        out[k] = c[k]
    return out


@dataclass
class Harness:
    cfg: DaemonConfig
    unit: VirtualUnit
    store: CalibrationStore
    session: Session | None = None
    now: float = 0.0
    outbox: list[Any] = field(default_factory=list)
    detector: StillDetector | None = None

    @classmethod
    def make(cls, tmp: Path, seed: int = 1, faults: Faults | None = None, **overrides: Any) -> Harness:
        cfg = load_config(None, {"state_dir": str(tmp / "state"),
                                 "control_socket": str(tmp / "c.sock"), **overrides})
        unit = VirtualUnit(TruthModel(), tumble(1.2, 0.4), RATE_HZ, seed, 4242, faults=faults)
        return cls(cfg, unit, CalibrationStore(cfg.state_dir))

    def send(self, msg: Any) -> None:
        # replies follow the samples rendered so far on the wire: note the seq just before them
        last_seq = self.unit.session_index - 1 if self.unit.session_index else None
        self.outbox.extend((reply, last_seq) for reply in self.unit.handle(msg))

    def switch_on(self) -> None:
        hello = self.unit.power_on()
        if not hello:
            return
        prior = self.store.latest(hello[0].serial, acked_only=True)
        self.detector = StillDetector.for_rate(RATE_HZ, self.cfg.still)
        learner = make_learner(self.cfg, prior, RATE_HZ)
        self.session = Session(self.cfg, hello[0], learner, self.store, self.send,
                               self.now, RATE_HZ, None if prior is None else prior.version)

    def run(self, seconds: float, until: Any = None) -> None:
        step = 20
        for _ in range(int(seconds * RATE_HZ / step)):
            self.now += step / RATE_HZ
            block = to_ring(self.unit.render(step))
            if self.session is None or self.detector is None:
                continue
            replies, self.outbox = self.outbox, []
            for msg, last_seq in replies:
                self.session.on_message(msg, self.now, last_seq)
            self.session.heard(float(block["t"][-1]))  # as the engine does, before the detector
            decided, still = self.detector.feed(block)
            self.session.feed(decided, still, self.now)
            self.session.tick(self.now)
            if until is not None and until(self):
                return
