"""Could the fitted model itself meet "within 0.1 decade at every tau"? The fidelity test on the truth.

    .venv/bin/python benchmarks/fidelity_null.py [--logs mikoff_imu1,...] [--draws 100] [--jsonl OUT.jsonl]

Per shipped log (``real_logs.logs``), session and axis: ``draws`` logs are simulated from the model
the fidelity figure simulates (``engine.analyze``'s extended fit + the session's error model, as
``fidelity.fidelity_block`` does), each with the session's length, and their Allan deviations at the
session's octave taus are compared with the draws' median. If the model were the sensor's truth, the
measured curve would be one such draw, so ``p_any_over_0.1`` is the chance that a perfect model still
misses 0.1 decade at some tau of that session and axis (``p_last_over_0.1``: at the last octave).
Also the measured curve against the draws' median (``meas_worst``, ``meas_last``) and the measured
last octave's rank among the draws (``rank_last``: near 0 or 1 where the model misses
systematically). The figure the analysis reports uses an ensemble of 8 (``fidelity.ENSEMBLE``); a
median of ``draws`` is the model's curve with less noise of its own.

The summary: the expected number of session-axes over 0.1 at some tau if every model were true, and
the chance of none.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gyrocal.analysis import engine, fidelity
from gyrocal.analysis.noisemodel import overlapping_avar

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_logs import logs as real_logs  # noqa: E402 (the one list of shipped logs)

LIMIT_DEC = 0.1


def fidelity_inputs(log):  # noqa: ANN001, ANN201 (LogData -> fidelity_block's arguments)
    """The arguments ``analyze`` passes to ``fidelity_block`` (prob, fit before, fit after, white
    before, models, seed), caught on the way."""
    caught: dict = {}
    orig = engine.fidelity_block

    def catch(*a, **k):  # noqa: ANN002, ANN003, ANN202
        caught["args"] = a
        return orig(*a, **k)

    engine.fidelity_block = catch
    try:
        engine.analyze(log)
    finally:
        engine.fidelity_block = orig
    return caught["args"]


def session_rows(name: str, draws: int) -> list[dict]:
    """One row per session and axis of one log (see the module docstring)."""
    prob, _, fit_after, _, models, _ = fidelity_inputs(real_logs()[name]())
    owns, _ = fidelity.session_models(prob, fit_after, models)
    rows = []
    for si, s in enumerate(np.unique(prob.usable.session)):
        sel = prob.usable.session == s
        n = int(sel.sum())
        m = fidelity.session_taus(n)
        for k, a in enumerate("xyz"):
            mod = owns.get((si, k), models[k])
            rng = np.random.default_rng([si, k, 99])
            sim = np.log10(np.array([np.sqrt(overlapping_avar(fit_after[sel, k] + mod.simulate(n, rng), m))
                                     for _ in range(draws)]))
            med = np.median(sim, axis=0)
            meas = 0.5 * np.log10(overlapping_avar(prob.y[sel, k], m))
            dev = np.abs(sim - med)
            rows.append({"log": name, "session": int(s), "axis": a, "samples": n, "octaves": len(m),
                         "last_tau_s": round(float(m[-1] / prob.rate_hz), 3),
                         "p_any_over_0.1": round(float(np.mean(dev.max(axis=1) > LIMIT_DEC)), 3),
                         "p_last_over_0.1": round(float(np.mean(dev[:, -1] > LIMIT_DEC)), 3),
                         "sd_last_dec": round(float(sim[:, -1].std()), 3),
                         "meas_worst": round(float(np.max(np.abs(meas - med))), 3),
                         "meas_last": round(float(meas[-1] - med[-1]), 3),
                         "rank_last": round(float(np.mean(sim[:, -1] < meas[-1])), 3)})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", help="comma-separated subset of " + ", ".join(real_logs()))
    ap.add_argument("--draws", type=int, default=100, help="simulated logs per session and axis")
    ap.add_argument("--jsonl", help="write one row per session and axis here")
    args = ap.parse_args(argv)
    names = args.logs.split(",") if args.logs else list(real_logs())
    rows = []
    out = open(args.jsonl, "w") if args.jsonl else None  # noqa: SIM115 (rows are written as they come)
    for name in names:
        for row in session_rows(name, args.draws):
            rows.append(row)
            print(json.dumps(row), flush=True)
            if out:
                out.write(json.dumps(row) + "\n")
                out.flush()
    p = np.array([r["p_any_over_0.1"] for r in rows])
    over = [r for r in rows if r["meas_worst"] > LIMIT_DEC]
    where = ", ".join(f"{r['log']} {r['session']} {r['axis']} {r['meas_worst']}" for r in over)
    print(f"{len(rows)} session-axes; if every model were true: {p.sum():.1f} expected over {LIMIT_DEC} "
          f"decade at some tau ({sum(r['p_last_over_0.1'] for r in rows):.1f} at the last octave), "
          f"P(none) = {np.prod(1 - p):.1e}; measured against the {args.draws}-draw median: {len(over)} over "
          f"({where})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
