"""The push gate on a unit whose bias wanders: when the daemon pushes, and the drift the unit keeps.

    .venv/bin/python benchmarks/bench_wander_gate.py [--seeds 4] [--session 1200] [--bias-dph 108] [--json]

The unit (sim/truth.py, in simulated time through the daemon's own Session, tests/daemon_harness.py):
seed 000 gravity drift, a switch-on bias of std ``--bias-dph``, white noise 0.1 deg/s per sample at
400 Hz (ARW 0.3 deg/sqrt(h)), a bias random walk of 1e-4 deg/s/sqrt(s) (21.6 deg/h/sqrt(h)) and a
flicker floor B of 10 deg/h (band 1-3000 s). Methods:

- ``rls``: the daemon's default; the plain push gate (left x min_cut <= removed, min_cut 20);
- ``kf``: the bias Kalman filter with the true intensities in its spec, which gives the gate its
  floor (refine.py: the wander's drift over ``push.wander_horizon_s``).

Per run: ``push_s`` (simulated seconds from switch-on to the ACK, null when none came), and from the
unit's truth, the drift the unit put out (``drift_w - comp_w``, walk and flicker included), as RMS
over the still dwells' means [deg/h]: ``kept_dph`` over the whole session, ``kept_after_dph`` over
its last third, beside ``raw_dph`` (the same dwells with nothing applied).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_bias_state import dwell_rms_dph  # noqa: E402  (benchmarks/: the same drift figure)

from gyrocal.daemon.config import load_config  # noqa: E402
from gyrocal.daemon.store import CalibrationStore  # noqa: E402
from gyrocal.model.terms import SEED000_TERMS  # noqa: E402
from gyrocal.sim.schedule import tumble  # noqa: E402
from gyrocal.sim.truth import DPH, Effects, TruthModel  # noqa: E402
from gyrocal.sim.unit import VirtualUnit  # noqa: E402
from tests.daemon_harness import RATE_HZ, Harness  # noqa: E402

NOISE_DPS = 0.1
WALK = 1e-4
B_DPS = 10 * DPH


class RecordingUnit(VirtualUnit):
    """A VirtualUnit that keeps the truth columns of what it sent (drift, compensation, still)."""

    def __init__(self, *a: Any, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.kept: list[np.ndarray] = []

    def render(self, n: int):  # noqa: ANN201 (VirtualUnit's Chunk)
        chunk = super().render(n)
        c = chunk.columns
        self.kept.append(np.column_stack([c["t"], *(c[f"drift_w{a}"] for a in "xyz"),
                                          *(c[f"comp_w{a}"] for a in "xyz"), c["still"]]))
        return chunk


def run(method: str, seed: int, session_s: float, bias_dph: float, work: Path) -> dict[str, Any]:
    work.mkdir(parents=True, exist_ok=True)
    est: dict[str, Any] = {"method": method,
                           "convergence": {"max_change_dps": 5e-3, "max_sigma_dps": 2e-3, "window": 5000}}
    if method == "kf":
        spec = work / "unit.terms.yaml"
        doc = {"terms": list(SEED000_TERMS), "random_walk": {"dps_per_sqrt_s": WALK},
               "bias_instability": {"dps": B_DPS, "tau_s": 300.0}}
        spec.write_text(yaml.safe_dump(doc), encoding="utf-8")
        est["terms"] = str(spec)
    cfg = load_config(None, {"state_dir": str(work / "state"), "control_socket": str(work / "c.sock"),
                             "estimator": est})
    effects = Effects(random_walk_dps_per_sqrt_s=np.full(3, WALK), bias_instability_dps=np.full(3, B_DPS),
                      flicker_band_s=(1.0, 3000.0))
    truth = TruthModel(noise_dps=NOISE_DPS, effects=effects, switch_on_bias_dps=bias_dph * DPH)
    unit = RecordingUnit(truth, tumble(1.2, 0.4), RATE_HZ, seed, 4242)
    h = Harness(cfg, unit, CalibrationStore(cfg.state_dir))
    h.switch_on()
    push_s = None
    t0 = time.process_time()
    while h.now < session_s:
        h.run(10.0)
        s = h.session
        if push_s is None and s is not None and s.last_push.get("status") == "acked":
            push_s = round(h.now, 1)
    rows = np.vstack(unit.kept)
    drift, comp, still_ = rows[:, 1:4], rows[:, 4:7], rows[:, 7] > 0.5
    last = still_ & (rows[:, 0] >= rows[-1, 0] * 2 / 3)
    return {"method": method, "seed": seed, "push_s": push_s, "cpu_s": round(time.process_time() - t0, 1),
            "kept_dph": round(dwell_rms_dph(still_, drift - comp), 2),
            "kept_after_dph": round(dwell_rms_dph(last, drift - comp), 2),
            "raw_dph": round(dwell_rms_dph(still_, drift), 2),
            "raw_after_dph": round(dwell_rms_dph(last, drift), 2),
            "reason": h.session.reason if h.session is not None else ""}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--session", type=float, default=1200.0, metavar="S", help="simulated session [s]")
    ap.add_argument("--bias-dph", type=float, default=108.0, help="switch-on bias std [deg/h] (default 108)")
    ap.add_argument("--methods", default="rls,kf")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(1, args.seeds + 1):
            for method in args.methods.split(","):
                r = run(method, seed, args.session, args.bias_dph, Path(tmp) / f"{method}-{seed}")
                rows.append(r)
                if not args.json:
                    print(json.dumps(r), flush=True)
    summary: dict[str, Any] = {}
    for method in args.methods.split(","):
        mine = [r for r in rows if r["method"] == method]
        summary[method] = {"pushed": sum(r["push_s"] is not None for r in mine), "runs": len(mine),
                           **{f"{k}_mean": round(float(np.mean([r[k] for r in mine])), 2)
                              for k in ("kept_dph", "kept_after_dph", "raw_after_dph")}}
    out = {"session_s": args.session, "bias_dph": args.bias_dph, "noise_dps": NOISE_DPS, "rate_hz": RATE_HZ,
           "walk_dps_per_sqrt_s": WALK, "bias_instability_dph": B_DPS / DPH, "runs": rows, "summary": summary}
    print(json.dumps(out, indent=1) if args.json else json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
