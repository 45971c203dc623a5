"""Benchmark of ``gyrocal analyze``: time on a 30-minute 100 Hz log, and the null false-alarm rate.

    .venv/bin/python benchmarks/bench_analyze.py [--seeds N] [--json OUT.json]

Timing: one 30-minute, 100 Hz tumble log (3 sessions of 10 min) with a hidden temperature effect,
analysed end to end through ``gyrocal analyze`` (read, fit, select, Allan, JSON). The false-alarm
rate: N seeded logs with no hidden effect (the test-sized logs: 3 sessions x 180 s at 25 Hz), the
share with any finding, with a 95% Clopper-Pearson upper bound. Also the hit rate on N seeded logs
with one hidden effect (first finding names it).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from scipy import stats

from gyrocal.analysis.hidden import write_hidden_log
from gyrocal.cli import main as cli


def _analyze(path: Path) -> dict:
    out = path.with_suffix(".json")
    rc = cli(["analyze", str(path), "--json", str(out), "--quiet"])
    if rc != 0:
        raise SystemExit(f"analyze failed on {path} (exit {rc})")
    return json.loads(out.read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=100, help="null and hidden-effect logs (default 100)")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--skip-timing", action="store_true")
    args = ap.parse_args(argv)
    fig: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        if not args.skip_timing:
            p = d / "long.csv"
            write_hidden_log(p, 7, causes=["temperature"], n_sessions=3, session_s=600.0, rate_hz=100.0)
            t0 = time.perf_counter()
            r = _analyze(p)
            fig["long_log"] = {"minutes": 30, "rate_hz": 100, "samples": r["samples"]["total"],
                               "seconds": round(time.perf_counter() - t0, 2),
                               "first_cause": r["findings"][0]["cause"] if r["findings"] else None}
            print(f"30-min 100 Hz log: {fig['long_log']['seconds']} s "
                  f"({fig['long_log']['samples']} samples)", flush=True)
        alarms, hits, t0 = 0, 0, time.perf_counter()
        for i in range(args.seeds):
            seed = 10_000 + i
            p = d / f"null{i}.csv"
            write_hidden_log(p, seed, causes=[])
            alarms += bool(_analyze(p)["findings"])
            p = d / f"hid{i}.csv"
            h = write_hidden_log(p, seed)
            f = _analyze(p)["findings"]
            hits += bool(f) and f[0]["cause"] == h.causes[0]
            print(f"\r{i + 1}/{args.seeds}: false alarms {alarms}, hits {hits}", end="", file=sys.stderr)
        print(file=sys.stderr)
        n = args.seeds
        upper = float(stats.beta.ppf(0.95, alarms + 1, n - alarms)) if alarms < n else 1.0
        fig["null"] = {"seeds": n, "false_alarms": alarms, "rate": alarms / n, "upper95": round(upper, 4),
                       "seconds_per_log": round((time.perf_counter() - t0) / (2 * n), 3)}
        fig["hidden_one_effect"] = {"seeds": n, "first_finding_correct": hits, "rate": hits / n}
    print(f"null false-alarm rate: {alarms}/{n} = {alarms / n:.3f} (95% upper bound {upper:.3f})")
    print(f"hidden single effect named first: {hits}/{n}")
    if args.json:
        Path(args.json).write_text(json.dumps(fig, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
