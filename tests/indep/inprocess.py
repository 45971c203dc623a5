"""The independent unit's physics driving the daemon's Session in process: many seeds in seconds.

The live runs (tests/test_indep_unit.py, benchmarks/bench_indep.py) put the independent unit and the
real daemon in separate processes on a pty or CAN, in real time, 30-120 s a run. That is the test
of the wire; it is too slow for the statistics of the push gate's prediction, which need hundreds of
axes. Here the same truth (tests/indep/truth.py: per-unit gravity terms, a new bias per switch-on,
white noise), the same random 24-pose schedule and the same temperature drive the daemon's Session
and StillDetector through tests/grade_harness.py, on the samples' own clock. The messages go through
the daemon's in-process message objects, not the wire, and the applied set is evaluated with the
daemon's term evaluator (gravity terms on a/|a|, as docs/protocol.md says).
Units: deg/s, g, degC, s.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gyrocal.daemon.config import load_config
from gyrocal.daemon.store import CalibrationStore
from gyrocal.model.prep import block_terms
from gyrocal.protocol.messages import CoeffWrite, Hello
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import TruthModel
from gyrocal.sim.unit import SEQ_MODULO, Chunk, VirtualUnit
from tests.grade_harness import GradeRun
from tests.indep.truth import PoseSchedule, Truth, temperature

ACCEL_LSB_G = 1e-4  # the pty link's accel resolution (tests/indep/links.py)
TEMP_LSB_C = 0.01


class IndepPhysicsUnit(VirtualUnit):
    """A VirtualUnit whose samples come from the independent unit's truth and pose schedule.

    Only ``power_on``, ``render`` and the truth readers differ; writes, reads and the applied set
    are VirtualUnit's (in process, no wire).
    """

    def __init__(self, grade: str, rate_hz: float, seed: int, serial: int, noise_dps: float | None = None):
        super().__init__(TruthModel(), tumble(1.2, 0.4), rate_hz, seed, serial)
        self.grade = grade
        self.indep = Truth.for_unit(serial, grade, noise_dps, 0.0)
        self._index = 0

    def power_on(self) -> list[Any]:
        self.boot_count += 1
        seed = self.seed * 100_003 + self.boot_count  # as tests/indep/unit.py switches on
        self.rng = np.random.default_rng(seed)
        self.indep.new_bias(self.grade, self.rng)
        self.poses = PoseSchedule(seed)
        self.temp0 = float(self.rng.uniform(18.0, 28.0))
        self._index = 0
        self.stream = None
        return [Hello(serial=self.serial, fw_version=self.fw_version, boot_count=self.boot_count,
                      rate_hz=int(round(self.rate_hz)))]

    @property
    def session_index(self) -> int:
        return self._index

    def render(self, n: int) -> Chunk:
        k = self._index + np.arange(n)
        t = k / self.rate_hz
        rate, force = self.poses.state(t)
        temp_true = temperature(t, self.temp0)
        g = force / np.linalg.norm(force, axis=1, keepdims=True)
        raw = rate + self.indep.drift(g, temp_true) + self.rng.normal(0, self.indep.noise_dps, (n, 3))
        accel = np.round((force + self.rng.normal(0, self.indep.accel_noise_g, (n, 3))) / ACCEL_LSB_G)
        accel *= ACCEL_LSB_G
        cols = {"t": t, "ax": accel[:, 0], "ay": accel[:, 1], "az": accel[:, 2],
                "temp": np.round(temp_true / TEMP_LSB_C) * TEMP_LSB_C}
        dtemp = self._trate.update(t, cols["temp"])
        comp = np.zeros((n, 3)) if self.applied is None else self._compensation(self.applied, cols, t, dtemp)
        for j, a in enumerate("xyz"):
            cols[f"w{a}"] = raw[:, j] - comp[:, j]
        self._index += n
        self.samples_sent += n
        return Chunk(seq=k % SEQ_MODULO, columns=cols)

    def drift_rms_dps(self) -> tuple[np.ndarray, np.ndarray]:
        """True drift RMS (3,) [deg/s] over the session's 24 poses, before and after the applied set."""
        g = self.poses.gravity_at_poses()
        k = len(g)
        true = self.indep.drift(g, np.full(k, 25.0))
        if self.applied is None:
            return np.sqrt(np.mean(true**2, axis=0)), np.sqrt(np.mean(true**2, axis=0))
        inputs = {"ax": g[:, 0], "ay": g[:, 1], "az": g[:, 2], "temp": np.full(k, 25.0),
                  "dtemp": np.zeros(k), "t_on": np.full(k, np.inf), "t": np.zeros(k)}
        comp = self.applied.spec.design(inputs) @ self.applied.coeffs_dps.T
        return np.sqrt(np.mean(true**2, axis=0)), np.sqrt(np.mean((true - comp) ** 2, axis=0))

    def status(self) -> dict[str, Any]:
        before, after = self.drift_rms_dps()
        return {"drift_rms_raw_dps": dict(zip("xyz", before.tolist(), strict=True)),
                "drift_rms_compensated_dps": dict(zip("xyz", after.tolist(), strict=True))}


FACTORY_VERSION = 7
"""The version of the factory set below, as the unit's flash holds it."""


def factory_dtemp_set() -> np.ndarray:
    """A factory set on terms 0x549E (3, 14) [deg/s per term unit] whose dT/dt term the unit's truth
    does not have: 0.02 / -0.015 / 0.01 deg/s per degC/s, besides a constant and small gravity terms.
    The daemon must add it back with the unit's own dtemp before it learns (protocol.md, section 6)."""
    coeffs = np.zeros((3, 14))
    coeffs[:, 0] = 0.01
    coeffs[:, 1:10] = np.random.default_rng(3).uniform(-0.002, 0.002, (3, 9))
    coeffs[:, 12] = [0.02, -0.015, 0.01]  # deg/s per degC/s
    return coeffs


def held_dtemp_run(tmp: Path, seed: int, rate_hz: float = 400.0) -> tuple[GradeRun, IndepPhysicsUnit]:
    """A fibre unit holding ``factory_dtemp_set`` and a session for it, not yet switched on."""
    cfg = load_config(None, {"state_dir": str(tmp / "state"), "control_socket": str(tmp / "c.sock")})
    unit = IndepPhysicsUnit("fibre", rate_hz, seed, 0x5EED0000 + seed)
    unit.applied = VirtualUnit._build(CoeffWrite(FACTORY_VERSION, 0x549E, factory_dtemp_set().tolist()))
    return GradeRun(cfg, unit, CalibrationStore(cfg.state_dir), rate_hz), unit


def replaced_factory_set(run: GradeRun) -> bool:
    """``GradeRun.run``'s stop: a push was acked over the factory set."""
    a = run.unit.applied
    return bool(run.pushes) and a is not None and a.version > FACTORY_VERSION


def first_push(tmp: Path, grade: str, rate_hz: float, seed: int, max_s: float = 150.0,
               **overrides: Any) -> dict[str, Any]:
    """Run one switch-on until the first push is acked; the unit's truth and the daemon's prediction.

    Returns before/after [deg/h] per axis over the unit's 24 poses, the time from HELLO [s], and the
    prediction recorded with the push (``expected``, ``left``, ``left_poses``, ``left_sphere``
    [deg/h]); ``pushed`` False if none came within ``max_s``.
    """
    cfg = load_config(None, {"state_dir": str(tmp / "state"), "control_socket": str(tmp / "c.sock"),
                             **overrides})
    unit = IndepPhysicsUnit(grade, rate_hz, seed, 0x5EED0000 + seed)
    run = GradeRun(cfg, unit, CalibrationStore(cfg.state_dir), rate_hz)
    run.switch_on()
    oracle: dict[str, float] = {}

    def until(r: GradeRun) -> bool:
        if r.pushes and not oracle and r.session is not None:
            oracle.update(_at_unit_poses(r.session, unit))
        return bool(r.pushes) and unit.applied is not None

    run.run(max_s, until)
    row: dict[str, Any] = {"grade": grade, "rate_hz": rate_hz, "seed": seed, "pushed": bool(run.pushes)}
    if not run.pushes or unit.applied is None:
        row["pushed"] = False
        return row
    before, after = unit.drift_rms_dps()
    pred = run.pushes[0]["push"].get("predicted_drift_dph") or {}
    row.update({"t_first_push_s": round(run.pushes[0]["t"], 2),
                "before": dict(zip("xyz", (before * 3600).tolist(), strict=True)),
                "after": dict(zip("xyz", (after * 3600).tolist(), strict=True)),
                "predicted_drift_dph": pred, "at_unit_poses_dph": oracle})
    return row


def _at_unit_poses(session: Any, unit: IndepPhysicsUnit) -> dict[str, float]:
    """The daemon's own prediction [deg/h] evaluated at the unit's 24 poses, which it cannot know.

    What the prediction would be if the daemon knew where the unit will be judged: the reference
    for how close any estimate from the poses seen and the sphere can come.
    """
    g = unit.poses.gravity_at_poses()
    k = len(g)
    cols = {key: np.full(k, v) for key, v in session._context.items()}
    cols.update({"ax": g[:, 0], "ay": g[:, 1], "az": g[:, 2]})
    cols.setdefault("t", np.zeros(k))
    phi = block_terms(session.spec, cols)
    p = session.learner.prediction(phi, session._sphere_phi(), None, session.holdout.blocks)
    return dict(zip("xyz", (np.asarray(p["left_poses"]) * 3600.0).tolist(), strict=True))
