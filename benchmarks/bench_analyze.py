"""Benchmark of ``gyrocal analyze``: time on a 30-minute 100 Hz log, and the null false-alarm rate.

    .venv/bin/python benchmarks/bench_analyze.py [--seeds N] [--json OUT.json]
    .venv/bin/python benchmarks/bench_analyze.py --long [--hours 3]      # linear cost: time + peak memory
    .venv/bin/python benchmarks/bench_analyze.py --backgrounds --seeds N  # coloured/flicker/quantised nulls
    .venv/bin/python benchmarks/bench_analyze.py --map --seeds N --plot map.png  # detection vs size
    .venv/bin/python benchmarks/bench_analyze.py --map --real --json m.json --plot m.png  # on real logs

``--long``: one 3-hour, 100 Hz still-and-tumble log (3 sessions of 1 h, 1.08 M samples, hidden
warm-up), analysed end to end through ``gyrocal analyze``; wall time and the process' peak resident
memory (resource.getrusage). ``--backgrounds``: the null false-alarm rate per noise background
(``gyrocal.analysis.hidden.add_background``); a false alarm is a regression cause (temperature, its
rate, warm-up, periodic, scale factor); noise causes and random_walk on a wandering background are
counted apart, because they describe that background.

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
    ap.add_argument("--long", action="store_true", help="3-hour 100 Hz log: time and peak memory")
    ap.add_argument("--hours", type=float, default=3.0)
    ap.add_argument("--backgrounds", action="store_true", help="false alarms on non-white nulls")
    ap.add_argument("--first-seed", type=int, default=20_000, help="--backgrounds: first seed")
    ap.add_argument("--kinds", help="--backgrounds: comma-separated subset of the backgrounds")
    ap.add_argument("--hard", action="store_true", help="score on the harder hidden set")
    ap.add_argument("--map", action="store_true", help="detection rate against effect size")
    ap.add_argument("--sizes", default="0.05,0.1,0.2,0.5,1.0", help="--map sizes [sigma]")
    ap.add_argument("--plot", help="--map: write the plot here (PNG)")
    ap.add_argument("--real", action="store_true",
                    help="--map: inject into every shipped real log (benchmarks/inject_real.py --map)")
    args = ap.parse_args(argv)
    if args.hard:
        return _hard(args.json)
    if args.map and args.real:
        return _map_real(args.json, args.plot)
    if args.map:
        return _map([float(x) for x in args.sizes.split(",")], args.seeds, args.json, args.plot)
    if args.long:
        return _long(args.hours, args.json)
    if args.backgrounds:
        return _backgrounds(args.seeds, args.json, args.first_seed, args.kinds)
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


def _long(hours: float, out: str | None) -> int:
    """Linear cost: analyse one long 100 Hz log; print wall time and peak memory [MB]."""
    import resource

    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "long.csv"
        session_s = hours * 3600.0 / 3
        write_hidden_log(p, 7, causes=["warmup"], n_sessions=3, session_s=session_s, rate_hz=100.0)
        t0, c0 = time.perf_counter(), time.process_time()
        r = _analyze(p)
        sec, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    # cpu_seconds (user + system of the analysis alone) is the figure a loaded machine spoils least: the
    # analysis is single-threaded apart from BLAS, so on an idle machine its wall time is about that
    fig = {"hours": hours, "rate_hz": 100, "samples": r["samples"]["total"], "seconds": round(sec, 1),
           "cpu_seconds": round(cpu, 1), "peak_rss_mb": round(peak_mb),
           "findings": [f["cause"] for f in r["findings"]]}
    print(json.dumps(fig))
    if out:
        Path(out).write_text(json.dumps(fig, indent=1) + "\n")
    return 0


def _map(sizes: list[float], seeds: int, out: str | None, plot: str | None) -> int:
    """Detection rate per cause against effect size (sigma = white noise per sample), simulated
    tumble logs (3 x 180 s at 25 Hz); the false-alarm rate (white nulls, same seeds) beside it."""
    from gyrocal.analysis.engine import analyze
    from gyrocal.analysis.hidden import HardCase, generate_hard
    from gyrocal.logformat import LogData

    causes = ("temperature", "temperature_rate", "warmup", "periodic", "random_walk")
    table: dict = {c: {} for c in causes}
    for c in causes:
        for size in sizes:
            hit = 0
            for i in range(seeds):
                cols, h = generate_hard(HardCase(40_000 + i, [c], size), session_s=180.0, n_sessions=3)
                res = analyze(LogData(cols, {}, [], "map")).result
                found = {f["cause"]: f["axes"] for f in res["findings"]}
                hit += set(h.axes[c]) <= set(found.get(c, []))
            table[c][size] = hit / seeds
            print(c, size, hit, "/", seeds, flush=True)
    alarms = 0
    for i in range(seeds):
        cols, _ = generate_hard(HardCase(40_000 + i, [], 0.0), session_s=180.0, n_sessions=3)
        alarms += bool(analyze(LogData(cols, {}, [], "null")).result["findings"])
    fig = {"sizes_sigma": sizes, "seeds": seeds, "detection": table, "null_false_alarms": alarms}
    print(json.dumps(fig))
    if out:
        Path(out).write_text(json.dumps(fig, indent=1) + "\n")
    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fg, ax = plt.subplots(figsize=(6, 4))
        for c in causes:
            ax.semilogx(sizes, [table[c][s] for s in sizes], marker="o", label=c)
        ax.axhline(alarms / seeds, color="k", ls="--", label=f"false alarms ({alarms}/{seeds})")
        ax.set_xlabel("effect size [sigma per sample]")
        ax.set_ylabel("detection rate (all affected axes)")
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
        fg.tight_layout()
        fg.savefig(plot, dpi=110)
    return 0


def _map_real(out: str | None, plot: str | None) -> int:
    """The detection map on real data: ``inject_real.py --map`` (every shipped log, cleaned of its
    own named effects; 3 axes / seeds per cause and size), then its summary, table and plot."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import inject_real

    with tempfile.TemporaryDirectory() as tmp:
        rows = str(Path(tmp) / "map.jsonl")
        inject_real.main(["--map", "--jsonl", rows])
        extra = (["--json", out] if out else []) + (["--plot", plot] if plot else [])
        return inject_real.main(["--map", "--summary", rows, *extra])


def _hard(out: str | None) -> int:
    """Score on ``HARD_SET``: a case is right when the regression causes found are exactly the hidden
    ones (on a flicker background an extra random_walk is allowed: that wander is predictable, which
    is what random_walk means); a null is right with no regression cause. Noise causes are free."""
    from gyrocal.analysis.engine import analyze
    from gyrocal.analysis.hidden import HARD_SET, generate_hard
    from gyrocal.logformat import LogData

    regression = {"temperature", "temperature_rate", "warmup", "periodic", "scale_factor", "random_walk"}
    rows, right, alarms = [], 0, 0
    for case in HARD_SET:
        cols, _ = generate_hard(case)
        found = {f["cause"] for f in analyze(LogData(cols, {}, [], "hard")).result["findings"]}
        reg = found & regression
        if case.background in ("flicker", "real_like"):
            reg -= {"random_walk"} - set(case.causes)
        ok = reg == set(case.causes)
        right += ok
        alarms += bool(reg - set(case.causes))
        rows.append({"seed": case.seed, "causes": case.causes, "size_sigma": case.size_sigma,
                     "background": case.background, "found": sorted(found), "right": ok})
        print(json.dumps(rows[-1]), flush=True)
    fig = {"cases": len(rows), "right": right, "with_a_false_cause": alarms, "rows": rows}
    print(f"hard set: {right}/{len(rows)} right, {alarms} with a cause that was not hidden")
    if out:
        Path(out).write_text(json.dumps(fig, indent=1) + "\n")
    return 0


def _backgrounds(n: int, out: str | None, first: int = 20_000, kinds: str | None = None) -> int:
    """Null false-alarm rate per noise background (analysis in-process, seeded), and over all of them.

    Each log is printed as it is done (seed, background, findings), so a long run can be read while
    it goes; the total over backgrounds is the figure for the issue's <= 1 % per log."""
    from gyrocal.analysis.engine import analyze
    from gyrocal.analysis.hidden import BACKGROUNDS, add_background, generate
    from gyrocal.logformat import LogData

    regression = ("temperature", "temperature_rate", "warmup", "periodic", "scale_factor")
    fig: dict = {}
    WANDERING = ("flicker", "real_like")  # noqa: N806 (a constant of this function)
    for kind in (kinds.split(",") if kinds else BACKGROUNDS):
        alarms, other = 0, {}
        for i in range(n):
            cols, _ = generate(first + i, causes=[])
            cols = add_background(cols, kind, first + i)
            res = analyze(LogData(cols, {}, [], kind)).result["findings"]
            found = [f["cause"] for f in res]
            # random_walk is a false alarm where the background does not wander (white, coloured,
            # quantised); on flicker / real_like it describes the background, so it is counted apart
            alarms += any(c in regression or (c == "random_walk" and kind not in WANDERING) for c in found)
            print(json.dumps({"seed": first + i, "background": kind,
                              "findings": {f["cause"]: [f["axes"], f["p_value"]] for f in res}}),
                  file=sys.stderr, flush=True)
            for c in found:
                if c not in regression and not (c == "random_walk" and kind not in WANDERING):
                    other[c] = other.get(c, 0) + 1
        upper = float(stats.beta.ppf(0.95, alarms + 1, n - alarms)) if alarms < n else 1.0
        fig[kind] = {"logs": n, "false_alarms": alarms, "upper95": round(upper, 4), "noise_findings": other}
        print(kind, json.dumps(fig[kind]), flush=True)
    logs = sum(f["logs"] for f in fig.values())
    alarms = sum(f["false_alarms"] for f in fig.values())
    upper = float(stats.beta.ppf(0.95, alarms + 1, logs - alarms)) if alarms < logs else 1.0
    fig["all"] = {"logs": logs, "false_alarms": alarms, "rate": alarms / logs, "upper95": round(upper, 4)}
    print("all", json.dumps(fig["all"]), flush=True)
    if out:
        Path(out).write_text(json.dumps(fig, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
