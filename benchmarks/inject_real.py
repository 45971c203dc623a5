"""Effects injected into every shipped real log: how often are they named, and could any test name them?

    .venv/bin/python benchmarks/inject_real.py --jsonl rows.jsonl                  # 0.25 / 0.4 / 0.6 sigma
    .venv/bin/python benchmarks/inject_real.py --logs mikoff_imu0,tomi_example_data_tinit_calc
    .venv/bin/python benchmarks/inject_real.py --map --jsonl map.jsonl            # 0.05-1 sigma
    .venv/bin/python benchmarks/inject_real.py --causes random_walk --walk-null allan --logs mikoff_imu0
    .venv/bin/python benchmarks/inject_real.py --summary rows.jsonl [more.jsonl] --json OUT.json \
        [--plot docs/img/analysis_detection_map_real.png]

The logs are every shipped one (``benchmarks/real_logs.py``: mikoff imu0-4, imucal, four
tomisuarez logs, sunsided (six recordings as one log, and the 10-minute one), imu_tk, the PX4 .ulg).

Per log, first the clean log: the full analysis (``gyrocal analyze``) names the log's own effects;
its regression effects are subtracted (as ``real_logs.py`` does), and the cause selection is run on
that cleaned log. What it still names (a second line on mikoff imu1 / imu4, the walk on tomisuarez
static z and sunsided 10 min x) is the log's own and is never counted as wrong. The effects are then
injected into the cleaned log (``gyrocal.analysis.hidden.inject``):

- warm-up ``size`` x sigma x exp(-t_on / 60 s) (size = the amplitude at switch-on);
- periodic, a sinusoid of RMS ``size`` x sigma at 1.7 Hz (variant 0) / 1.3 Hz (1) / 2.3 Hz (2);
- random walk of intensity ``size`` x sigma / sqrt(T / 2), T the mean session length (its RMS over
  a session is about ``size`` x sigma), a fresh path per variant;

sigma = the log's per-sample noise (``noise_dps`` of the clean analysis, mean over axes). Each
variant puts the effect on another axis (rotating over the axes on which the cleaned log does not
already name that cause). Only the cause selection (regression causes by the LR test, then the walk)
is run on an injected log: the noise causes and fidelity need the simulated ensembles and do not
bear on naming (``--full`` runs the whole ``analyze``).

Scored per injection:
- ``named``: the cause is selected on the injected axis (a periodic at the injected frequency,
  within 3 frequency bins, 3 / span);
- ``wrong``: a regression cause other than the injected one is selected on an axis where the
  cleaned log did not name it;
- ``spill``: the injected cause is also selected on an axis it was not put on;
- ``extra_walk``: random_walk selected where the cleaned log did not name it, beside an injected
  warm-up or periodic (the slow states took part of it; not a wrong regression cause);
  ``walk_instead`` (in the summary): of those, the effect missed and random_walk named on its axis.

Oracle power: for each injected signal s (on the used samples), the noncentrality
lambda = s' V^-1 s - s' V^-1 X (X' V^-1 X)^-1 X' V^-1 s of a likelihood-ratio test that knows the
effect's shape, under the cleaned log's fitted error model V (the test's own, ``AxisLR.model``), X
the baseline (session offsets + nine gravity terms); its power at the analysis' threshold (p <
0.01/18, times the warm-up grid's 8 or the frequency search's look-elsewhere factor; the shipped
test pays 9 for the warm-up since its tau is chosen per axis, so the oracle is a touch generous).
It is the most ANY test could name on that log; the analysis' searched test has less. For a random
walk it is generous by far: it knows the path, where the walk test has to find a wander.
The variance-component oracle (``vc_oracle_power``, walk injections only): the power of the walk's
own test (``lrtest.walk_lr``) at the true intensity, under the cleaned log's own null model,
from simulated draws (``vc_oracle``). It knows the intensity but not the path, so it is the fair
yardstick for a walk; the summary gives both.
``outside_baseline`` is the share of s's energy the baseline cannot absorb (least squares).

Rows are written to ``--jsonl`` as they come (one per clean log, one per injection), so a long run
can be split by ``--logs`` over processes and summarised together.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gyrocal.analysis.baseline import Problem
from gyrocal.analysis.candidates import Candidate
from gyrocal.analysis.lrtest import AxisLR
from gyrocal.logformat import LogData

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_logs import cleaned_columns  # noqa: E402 (the one way to remove a log's own effects)
from real_logs import logs as real_logs  # noqa: E402 (the one list of shipped logs)

REGRESSION = ("temperature", "temperature_rate", "warmup", "periodic", "scale_factor")
CAUSES = ("warmup", "periodic", "random_walk")
SIZES = (0.25, 0.4, 0.6)
MAP_SIZES = (0.05, 0.1, 0.25, 0.4, 0.6, 1.0)
FREQS_HZ = (1.7, 1.3, 2.3)
WARMUP_TAU_S = 60.0
ORACLE_HIGH = 0.9
"""Injections whose oracle power is at least this are the ones the log can show."""


@dataclass
class Selection:
    """The analysis' cause selection on one log: per axis the causes named, and what the oracle needs."""

    prob: Problem
    cands: list[Candidate]
    lrs: list[AxisLR]
    axes: dict[str, list[str]]
    frequency_hz: float | None

    def by_cause(self) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {}
        for a, cs in self.axes.items():
            for c in cs:
                out.setdefault(c, []).append(a)
        return out


def select(columns: dict[str, np.ndarray]) -> Selection:
    """The cause selection of ``analyze`` (same steps, same tau re-run for periodic), without the
    error-model twin, the noise causes and fidelity."""
    from gyrocal.analysis import engine
    from gyrocal.analysis.candidates import all_candidates
    from gyrocal.analysis.lrtest import build_axis_lr

    prob = engine.problem_of(columns)
    cands = all_candidates(prob)
    lrs = [build_axis_lr(prob, cands, k) for k in range(3)]
    tau_s = engine.DEFAULT_TAU_S
    per_axis = engine._select(prob, cands, tau_s, lambda _m: None, lrs)
    per_freq = [c for c in cands if c.cause == "periodic"]
    if per_freq and any(s.cause == "periodic" for r in per_axis for s in r.steps):
        tau_p = float(per_freq[0].tau_s or tau_s)
        if tau_p < tau_s:
            per_axis = engine._select(prob, cands, tau_p, lambda _m: None, lrs)
    freq = float(per_freq[0].info["frequency_hz"]) if per_freq else None
    return Selection(prob, cands, lrs, {a: [s.cause for s in r.steps] for a, r in zip("xyz", per_axis,
                                                                                         strict=True)}, freq)


def select_full(columns: dict[str, np.ndarray], log: LogData) -> dict[str, list[str]]:
    """Per axis the causes the whole ``analyze`` names (regression causes and random_walk)."""
    from gyrocal.analysis.engine import analyze

    r = analyze(LogData(columns, log.metadata, log.extra_columns, log.source)).result
    out: dict[str, list[str]] = {a: [] for a in "xyz"}
    for f in r["findings"]:
        if f["cause"] in (*REGRESSION, "random_walk"):
            for a in f["axes"]:
                out[a].append(f["cause"])
    return out


def session_span(columns: dict[str, np.ndarray]) -> float:
    """Mean session length [s] (sessions may share a time origin: sunsided_all)."""
    t = np.asarray(columns["t"], float)
    s = np.asarray(columns.get("session", np.zeros_like(t)))
    return float(np.mean([np.ptp(t[s == k]) for k in np.unique(s)]))


def injections(size: float, sigma: float, span: float, variants: int, own: dict[str, list[str]],
               causes: Iterable[str] = CAUSES) -> Iterable[tuple[str, str, float, dict, int]]:
    """(cause, axis, amplitude, params, variant) for one size: each variant on another axis."""
    for cause in causes:
        free = [a for a in "xyz" if a not in own.get(cause, [])] or list("xyz")
        start = {"warmup": 0, "periodic": 1, "random_walk": 2}[cause]
        for v in range(variants):
            axis = free[(start + v) % len(free)]
            if cause == "warmup":
                yield cause, axis, size * sigma, {"tau_s": WARMUP_TAU_S}, v
            elif cause == "periodic":
                yield cause, axis, size * sigma * np.sqrt(2), {"frequency_hz": FREQS_HZ[v % len(FREQS_HZ)]}, v
            else:
                yield cause, axis, size * sigma / np.sqrt(span / 2), {}, v


def oracle(sel: Selection, axis: str, sig_full: np.ndarray, cause: str) -> dict:
    """Oracle power of one injected signal (M_total,) on the clean selection's problem and model."""
    from scipy import stats

    from gyrocal.analysis.baseline import gram_solve
    from gyrocal.analysis.gls import StateSpaceGLS
    from gyrocal.analysis.holdout import ALPHA
    from gyrocal.analysis.lrtest import search_factor

    prob, k = sel.prob, "xyz".index(axis)
    sig = sig_full[prob.usable.index]
    x = prob.base
    b, *_ = np.linalg.lstsq(x, sig, rcond=None)
    energy = float(np.sum(sig**2))
    outside = float(np.sum((sig - x @ b) ** 2) / energy) if energy > 0 else 0.0
    gls = StateSpaceGLS(sel.lrs[k].model, prob.cols["t"], prob.usable.session)
    g = gls.gram(np.column_stack([x, sig]))
    beta = gram_solve(g[:-1, :-1], g[:-1, -1], prob.n)
    lam = max(float(g[-1, -1] - g[:-1, -1] @ beta), 0.0)
    look = search_factor(prob, cause) if cause != "random_walk" else 1.0
    dof = 2 if cause == "periodic" else 1
    crit = float(stats.chi2.isf(ALPHA / look, dof))
    return {"outside_baseline": round(outside, 4), "lambda": round(lam, 2), "critical": round(crit, 1),
            "oracle_power": round(float(stats.ncx2.sf(crit, dof, max(lam, 1e-12))), 4)}


VC_DRAWS = 40
"""Simulated draws per walk injection for the variance-component oracle (SE of its power <= 0.08)."""


def vc_oracle(sel: Selection, axis: str, q_true: float, seed: int) -> dict:
    """Power of the walk's variance-component likelihood ratio at the true intensity (the fair yardstick).

    ``VC_DRAWS`` logs are simulated on the cleaned log's used samples (its time stamps, sessions and
    baseline design): the walk test's null model of that axis (white + colour at their low-frequency
    white level, ``lrtest.fast_part`` of the point model) plus a fresh walk of intensity q_true
    [(deg/s)^2 / s] per draw. Each draw gets the analysis' statistic (``lrtest.walk_statistic``: the
    profiled or the held-null profile as ``lrtest.WALK_NULL`` says, on the grid without the parabola,
    so a touch low) and its chi-bar-square p; the power is the share with
    p < ALPHA. It knows the walk's intensity, not its path: the most a test of the walk could do.
    The held-out confirmation the analysis adds is not in it.
    """
    from gyrocal.analysis.holdout import ALPHA
    from gyrocal.analysis.lrtest import chibar_p, fast_part, walk_statistic

    prob, k = sel.prob, "xyz".index(axis)
    null = fast_part(sel.lrs[k].point_model_for([]))
    t, sess = prob.cols["t"], prob.usable.session
    start = np.concatenate(([True], sess[1:] != sess[:-1]))
    dt = np.where(start, 0.0, np.maximum(np.diff(t, prepend=t[0]), 0.0))
    rng = np.random.default_rng(seed)
    steps = rng.normal(0.0, 1.0, (t.size, VC_DRAWS)) * np.sqrt(q_true * dt)[:, None]
    walk = np.empty_like(steps)
    for s0, s1 in zip(np.flatnonzero(start), [*np.flatnonzero(start)[1:], t.size], strict=True):
        walk[s0:s1] = np.cumsum(steps[s0:s1], axis=0)
    ys = walk + rng.normal(0.0, np.sqrt(null.lowfreq_white_var), walk.shape)
    d, _ = walk_statistic(prob, null, prob.base, ys)
    p = np.array([chibar_p(float(v)) for v in d])
    return {"vc_oracle_power": round(float(np.mean(p < ALPHA)), 4),
            "vc_oracle_d_median": round(float(np.median(d)), 2)}


def score(found: dict[str, list[str]], own: dict[str, list[str]], cause: str, axis: str,
          freq_ok: bool) -> dict:
    """named / wrong / spill / extra_walk of one injection (see the module docstring)."""
    new = {a: [c for c in found[a] if c not in own.get(a, [])] for a in "xyz"}
    named = cause in found[axis] and freq_ok
    wrong = sorted({c for a in "xyz" for c in new[a] if c in REGRESSION and c != cause})
    spill = sorted(a for a in "xyz" if a != axis and cause in new[a])
    extra_walk = cause != "random_walk" and any("random_walk" in new[a] for a in "xyz")
    return {"named": bool(named), "wrong": wrong, "spill": spill, "extra_walk": bool(extra_walk)}


def run_log(name: str, load: Callable[[], LogData], sizes: list[float], variants: int, full: bool,
            emit: Callable[[dict], None], causes: Iterable[str] = CAUSES) -> None:
    """Clean one log, then inject every cause at every size and variant; emit one row each."""
    from gyrocal.analysis.engine import analyze
    from gyrocal.analysis.hidden import inject

    log = load()
    t0 = time.perf_counter()
    an = analyze(log)
    res = an.result
    sigma = float(np.mean(list(res["noise_dps"].values())))
    cols = cleaned_columns(log, an)
    sel = select(cols)
    own = select_full(cols, log) if full else sel.axes
    own_by_cause: dict[str, list[str]] = {}
    for a, cs in own.items():
        for c in cs:
            own_by_cause.setdefault(c, []).append(a)
    span = session_span(cols)
    emit({"kind": "clean", "log": name, "samples": len(log), "used": int(sel.prob.n),
          "span_s": round(span, 1),
          "sessions": int(np.unique(sel.prob.usable.session).size), "sigma_dps": round(sigma, 5),
          "findings": {f["cause"]: f["axes"] for f in res["findings"]},
          "after_removal": own, "seconds": round(time.perf_counter() - t0, 1)})
    bins_hz = 3.0 / max(span, 1e-9)
    for size in sizes:
        for cause, axis, amp, params, v in injections(size, sigma, span, variants, own_by_cause, causes):
            t1 = time.perf_counter()
            inj = inject(cols, cause, amp, [axis], seed=7 + v, **params)
            sig = inj[f"w{axis}"] - cols[f"w{axis}"]
            if full:
                found = select_full(inj, log)
                freq_ok = True  # the whole analysis' periodic frequency is checked below via select
                if cause == "periodic" and "periodic" in found[axis]:
                    s2 = select(inj)
                    freq_ok = s2.frequency_hz is not None and abs(
                        s2.frequency_hz - params["frequency_hz"]) <= bins_hz
            else:
                s2 = select(inj)
                found = s2.axes
                freq_ok = cause != "periodic" or (
                    s2.frequency_hz is not None and abs(s2.frequency_hz - params["frequency_hz"]) <= bins_hz)
            row = {"kind": "inject", "log": name, "cause": cause, "axis": axis, "size_sigma": size,
                   "variant": v, "amplitude_dps": float(amp), **{k: float(p) for k, p in params.items()},
                   **score(found, own, cause, axis, freq_ok), **oracle(sel, axis, sig, cause),
                   **(vc_oracle(sel, axis, float(amp) ** 2, 1000 + v) if cause == "random_walk" else {}),
                   "found": {a: found[a] for a in "xyz" if found[a]},
                   "seconds": round(time.perf_counter() - t1, 1)}
            emit(row)


def _rate(rows: list[dict]) -> dict:
    n = len(rows)
    return {"n": n, "named": sum(r["named"] for r in rows), "wrong": sum(bool(r["wrong"]) for r in rows),
            "spill": sum(bool(r["spill"]) for r in rows), "extra_walk": sum(r["extra_walk"] for r in rows),
            "walk_instead": sum(r.get("walk_instead", False) for r in rows),
            "oracle_mean": round(float(np.mean([r["oracle_power"] for r in rows])), 3) if n else None}


def summarise(rows: list[dict], sizes: list[float]) -> dict:
    """Per log and overall: named rate, wrong causes, oracle power; and the same over the injections
    the log can show (oracle power >= ORACLE_HIGH); per cause and size for the map."""
    inj = [r for r in rows if r["kind"] == "inject" and r["size_sigma"] in sizes]
    clean = {r["log"]: r for r in rows if r["kind"] == "clean"}
    for r in inj:  # the effect missed and random_walk named on its axis instead (not a regression cause)
        own = clean[r["log"]]["after_removal"].get(r["axis"], []) if r["log"] in clean else []
        walk = "random_walk" in r["found"].get(r["axis"], []) and "random_walk" not in own
        r["walk_instead"] = bool(r["cause"] != "random_walk" and not r["named"] and walk)
    out: dict = {"sizes_sigma": sizes, "logs": {}, "overall": {}, "map": {}, "clean": clean}

    def high(rs: list[dict]) -> list[dict]:
        return [r for r in rs if r["oracle_power"] >= ORACLE_HIGH]

    keys = ("log", "cause", "axis", "size_sigma", "variant", "oracle_power", "wrong", "found")
    for name in clean:
        rs = [r for r in inj if r["log"] == name]
        out["logs"][name] = {"all": _rate(rs), "showable": _rate(high(rs)),
                             "by_cause": {c: _rate([r for r in rs if r["cause"] == c]) for c in CAUSES}}
    out["overall"] = {"all": _rate(inj), "showable": _rate(high(inj)),
                      "missed_showable": [{k: r[k] for k in keys} for r in high(inj) if not r["named"]],
                      "wrong_rows": [{k: r[k] for k in keys} for r in inj if r["wrong"]]}
    for c in CAUSES:
        out["map"][c] = {}
        for s in sizes:
            rs = [r for r in inj if r["cause"] == c and r["size_sigma"] == s]
            if rs:
                out["map"][c][s] = {**_rate(rs), "oracle_expected": round(float(np.sum([r["oracle_power"]
                                                                                         for r in rs])), 2)}
    out["walk"] = walk_summary(inj, sizes)
    alarms = {n: [c for a, cs in r["after_removal"].items() for c in cs if c in REGRESSION]
              for n, r in clean.items()}
    out["real_nulls"] = {"logs": len(clean), "with_regression_cause": sum(bool(v) for v in alarms.values()),
                         "which": {n: v for n, v in alarms.items() if v}}
    return out


def walk_summary(inj: list[dict], sizes: list[float]) -> dict:
    """The walk injections per size and overall: named, the known-path oracle and the variance-component
    oracle (its mean power, and the named share where it is >= ORACLE_HIGH)."""
    def one(rs: list[dict]) -> dict:
        vc = [r for r in rs if "vc_oracle_power" in r]
        hi = [r for r in vc if r["vc_oracle_power"] >= ORACLE_HIGH]
        kp = [r for r in rs if r["oracle_power"] >= ORACLE_HIGH]
        return {"n": len(rs), "named": sum(r["named"] for r in rs),
                "oracle_mean": round(float(np.mean([r["oracle_power"] for r in rs])), 3) if rs else None,
                "vc_n": len(vc),
                "vc_oracle_mean": (round(float(np.mean([r["vc_oracle_power"] for r in vc])), 3)
                                   if vc else None),
                "named_where_vc_high": sum(r["named"] for r in hi), "vc_high": len(hi),
                "named_where_known_path_high": sum(r["named"] for r in kp), "known_path_high": len(kp)}

    walks = [r for r in inj if r["cause"] == "random_walk"]
    return {"all": one(walks), "by_size": {s: one([r for r in walks if r["size_sigma"] == s]) for s in sizes}}


def walk_markdown(s: dict) -> str:
    """The walk table: named against both oracles, per size."""
    out = ["| size | named | known-path oracle (mean power) | variance-component oracle (mean power) "
           "| named where VC oracle >= 0.9 | named where known-path oracle >= 0.9 |",
           "|---|---|---|---|---|---|"]
    for key, r in [*s["walk"]["by_size"].items(), ("all", s["walk"]["all"])]:
        if not r["n"]:
            continue
        vc = f"{r['vc_oracle_mean']:.0%}" if r["vc_oracle_mean"] is not None else "-"
        out.append(f"| {key if key == 'all' else f'{key:g} sigma'} | {r['named']} / {r['n']} "
                   f"({r['named'] / r['n']:.0%}) | {r['oracle_mean']:.0%} | {vc} | "
                   f"{r['named_where_vc_high']} / {r['vc_high']} | "
                   f"{r['named_where_known_path_high']} / {r['known_path_high']} |")
    return "\n".join(out)


def markdown(s: dict) -> str:
    """The per-log table and the map table of docs/analysis.md."""
    def cell(r: dict) -> str:
        return f"{r['named']} / {r['n']}" if r["n"] else "-"

    out = ["| log | own findings (after removal) | sigma [deg/s] | named | warm-up | periodic | walk "
           "| wrong | walk instead | mean oracle | named where oracle >= 0.9 |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    rows = [*s["logs"].items(), ("**all**", {**s["overall"], "by_cause": None})]
    for name, v in rows:
        a, h = v["all"], v["showable"]
        c = s["clean"].get(name)
        own = "; ".join(f"{k} {','.join(ax)}" for k, ax in c["findings"].items()) if c else ""
        after = sorted({x for xs in c["after_removal"].values() for x in xs}) if c else []
        own = f"{own} ({', '.join(after) or 'none'})" if c else ""
        by = v["by_cause"] or {k: {"named": 0, "n": 0} for k in CAUSES}
        if v["by_cause"] is None:
            by = {k: {"named": sum(r["named"] for r in s["map"][k].values()),
                      "n": sum(r["n"] for r in s["map"][k].values())} for k in CAUSES}
        out.append(f"| {name} | {own} | {c['sigma_dps'] if c else ''} | {cell(a)} | {cell(by['warmup'])} | "
                   f"{cell(by['periodic'])} | {cell(by['random_walk'])} | {a['wrong']} | "
                   f"{a['walk_instead']} | {a['oracle_mean']} | {cell(h)} |")
    out += ["", "| cause | " + " | ".join(f"{x:g} sigma" for x in s["sizes_sigma"]) + " |",
            "|---|" + "---|" * len(s["sizes_sigma"])]
    for c in CAUSES:
        cells = []
        for x in s["sizes_sigma"]:
            r = s["map"][c].get(x)
            cells.append(f"{r['named'] / r['n']:.0%} ({r['named']}/{r['n']}; "
                         f"oracle {r['oracle_expected'] / r['n']:.0%})" if r else "-")
        out.append(f"| {c} | " + " | ".join(cells) + " |")
    wrong = [f"{sum(s['map'][c][x]['wrong'] for c in CAUSES if x in s['map'][c])}/"
             f"{sum(s['map'][c][x]['n'] for c in CAUSES if x in s['map'][c])}" for x in s["sizes_sigma"]]
    out.append("| wrong cause | " + " | ".join(wrong) + " |")
    return "\n".join(out)


def plot_map(summary: dict, path: str) -> None:
    """Detection rate and the oracle's expected rate against size, per cause, over every shipped log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fg, ax = plt.subplots(figsize=(6.4, 4.2))
    for c, color in zip(CAUSES, ("C0", "C1", "C2"), strict=True):
        sz = sorted(summary["map"][c], key=float)
        if not sz:
            continue
        rate = [summary["map"][c][s]["named"] / summary["map"][c][s]["n"] for s in sz]
        orc = [summary["map"][c][s]["oracle_expected"] / summary["map"][c][s]["n"] for s in sz]
        ax.semilogx([float(s) for s in sz], rate, marker="o", color=color, label=f"{c}: named")
        ax.semilogx([float(s) for s in sz], orc, ls=":", color=color, label=f"{c}: oracle power")
    inj = [r for c in CAUSES for r in summary["map"][c].values()]
    wrong = sum(r["wrong"] for r in inj)
    n = sum(r["n"] for r in inj)
    ax.axhline(wrong / max(n, 1), color="k", ls="--", label=f"a wrong regression cause ({wrong}/{n})")
    ax.set_xlabel("injected size [sigma per sample of the log]")
    ax.set_ylabel("share of injections named")
    ax.set_title("Injected into every shipped real log", fontsize=9)
    ax.legend(fontsize=6.5)
    ax.grid(True, which="both", alpha=0.3)
    fg.tight_layout()
    fg.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jsonl", help="append one row per clean log / injection here")
    ap.add_argument("--json", help="--summary: write the summary here")
    ap.add_argument("--map", action="store_true", help=f"sizes {MAP_SIZES} (the real-log detection map)")
    ap.add_argument("--sizes", help="comma-separated sizes [sigma]")
    ap.add_argument("--variants", type=int, default=3, help="axes / seeds / frequencies per cause and size")
    ap.add_argument("--logs", help="comma-separated subset of " + ", ".join(real_logs()))
    ap.add_argument("--skip", help="comma-separated logs to leave out")
    ap.add_argument("--full", action="store_true", help="run the whole analyze on each injected log")
    ap.add_argument("--causes", help="comma-separated subset of " + ", ".join(CAUSES) + " to inject")
    ap.add_argument("--walk-null", choices=("profiled", "allan"),
                    help="the walk test's null level (lrtest.WALK_NULL; default: the module's)")
    ap.add_argument("--summary", nargs="+", help="summarise these JSONL files (no analysis)")
    ap.add_argument("--plot", help="--summary: the detection-map plot (PNG)")
    ap.add_argument("--markdown", action="store_true", help="--summary: print the docs' tables")
    args = ap.parse_args(argv)
    default = MAP_SIZES if args.map else SIZES
    sizes = [float(s) for s in args.sizes.split(",")] if args.sizes else list(default)
    if args.summary:
        rows = [json.loads(line) for f in args.summary for line in Path(f).read_text().splitlines() if line]
        # the last clean row per log wins; injections are deduplicated by (log, cause, size, variant)
        uniq: dict = {}
        for r in rows:
            key = (r["log"],) if r["kind"] == "clean" else (
                r["log"], r["cause"], r["size_sigma"], r["variant"])
            uniq[(r["kind"], *key)] = r
        s = summarise(list(uniq.values()), sizes)
        for name, v in s["logs"].items():
            a, h = v["all"], v["showable"]
            print(f"{name:32s} named {a['named']:3d}/{a['n']:3d} wrong {a['wrong']} spill {a['spill']} "
                  f"extra_walk {a['extra_walk']} (instead {a['walk_instead']}) oracle {a['oracle_mean']}  "
                  f"| oracle>=0.9: {h['named']}/{h['n']}")
        a, h = s["overall"]["all"], s["overall"]["showable"]
        print(f"overall named {a['named']}/{a['n']}, wrong {a['wrong']}, spill {a['spill']}, extra_walk "
              f"{a['extra_walk']} (instead {a['walk_instead']}); where oracle >= {ORACLE_HIGH}: "
              f"named {h['named']}/{h['n']}, "
              f"wrong {h['wrong']}")
        print("real nulls:", json.dumps(s["real_nulls"]))
        for c in CAUSES:
            print(c, {k: f"{v['named']}/{v['n']} (oracle {v['oracle_expected']})"
                      for k, v in s["map"][c].items()})
        w = s["walk"]["all"]
        print(f"random_walk named {w['named']}/{w['n']}; known-path oracle {w['oracle_mean']}, "
              f"variance-component oracle {w['vc_oracle_mean']} (on {w['vc_n']}); named where VC oracle "
              f">= {ORACLE_HIGH}: {w['named_where_vc_high']}/{w['vc_high']}")
        if args.markdown:
            print(markdown(s))
            print()
            print(walk_markdown(s))
        if args.json:
            Path(args.json).write_text(json.dumps(s, indent=1) + "\n")
        if args.plot:
            plot_map(s, args.plot)
        return 0
    if args.walk_null:
        from gyrocal.analysis import lrtest

        lrtest.WALK_NULL = args.walk_null
    causes = args.causes.split(",") if args.causes else list(CAUSES)
    allowed = real_logs()
    names = args.logs.split(",") if args.logs else list(allowed)
    names = [n for n in names if n not in (args.skip.split(",") if args.skip else [])]
    fh = open(args.jsonl, "a") if args.jsonl else None  # noqa: SIM115 (closed below)

    def emit(row: dict) -> None:
        print(json.dumps(row), flush=True)
        if fh:
            fh.write(json.dumps(row) + "\n")
            fh.flush()

    try:
        for name in names:
            run_log(name, allowed[name], sizes, args.variants, args.full, emit, causes)
    finally:
        if fh:
            fh.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
