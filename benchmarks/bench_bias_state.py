"""The gain of the bias state on line: drift left after the push, with and without it (issue 12).

    .venv/bin/python benchmarks/bench_bias_state.py [--json] [--quick] [--seeds N] [--session S] [--reml-walk]

A virtual unit (the truth model: seed 000 gravity drift, switch-on bias, white noise, plus a bias
random walk and flicker) is calibrated on line over one tumble session, with the estimator fed the
still samples in 1 s chunks, as the daemon does. At the end of the session the set is pushed, and
the stream goes on. The figure of merit is the drift left in the output: [truth drift - pushed
compensation] averaged over each 1.5 s rest (so the flicker's sub-second part, which acts as noise,
is not counted as drift), RMS over the rests [deg/h]:

- ``at_push``: over the first tumble cycle after the push (every pose once, 36 s);
- ``after``: over the ``--after`` seconds after the push (the wander goes on; nobody can predict it);
- ``floor``: what the wander's own change leaves even for the best constant chosen knowing the
  future, and ``above floor`` = sqrt(method^2 - floor^2), the part a push can remove.

Methods: ``rls`` (lambda 1, the daemon's default), ``rls_forget`` (lambda 0.9999, ~100 s of still
samples: the other way to follow a wander, seed 003), ``kf_spec`` (method kf, intensities from an
Allan fit (``fit_noise_terms``) of a separate 4 h still recording of the same unit),
``kf_analyze`` (method kf, the bias blocks that ``gyrocal analyze`` itself writes from that
recording, ``extend.bias_spec``; ``--no-analyze`` leaves it out) and ``kf_true`` (method kf, the
truth's intensities), all with ``horizon_s`` = the window after the push; with ``--reml-walk`` also
``kf_analyze_reml`` (the analyze spec with the walk test's REML intensity in place of the joint Allan
fit's K: docs/analysis.md, "The walk's intensity in the finding"). Cases: ``walk+flicker``
(the issue's unit), ``flicker`` only, and ``none`` (a control: the bias state must cost nothing).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gyrocal.model.allan import allan_curve, fit_noise_terms  # noqa: E402
from gyrocal.model.bias_kalman import BiasModel  # noqa: E402
from gyrocal.model.methods import make_estimator  # noqa: E402
from gyrocal.model.prep import segment_ids  # noqa: E402
from gyrocal.model.terms import SEED000_TERMS, TermSpec  # noqa: E402
from gyrocal.sim.schedule import still, tumble  # noqa: E402
from gyrocal.sim.truth import DPH, Effects, SessionStream, TruthModel  # noqa: E402

RATE_HZ = 100.0
NOISE_DPS = 0.05            # white noise per sample at 100 Hz: ARW 0.005 deg/sqrt(s) = 0.3 deg/sqrt(h)
CASES = {                   # B 10 deg/h; walk 1e-4 deg/s/sqrt(s) = 21.6 deg/h/sqrt(h): a tactical-grade MEMS
    "walk+flicker": {"random_walk_dps_per_sqrt_s": 1e-4, "bias_instability_dps": 10 * DPH},
    "flicker": {"random_walk_dps_per_sqrt_s": 0.0, "bias_instability_dps": 10 * DPH},
    "none": {"random_walk_dps_per_sqrt_s": 0.0, "bias_instability_dps": 0.0},
}
FLICKER_BAND_S = (1.0, 3000.0)
SPEC = TermSpec.parse(SEED000_TERMS)


def unit(case: str) -> TruthModel:
    c = CASES[case]
    e = Effects(random_walk_dps_per_sqrt_s=np.full(3, c["random_walk_dps_per_sqrt_s"]),
                bias_instability_dps=np.full(3, c["bias_instability_dps"]), flicker_band_s=FLICKER_BAND_S)
    return TruthModel(noise_dps=NOISE_DPS, effects=e)


def still_recording(model: TruthModel, seed: int, seconds: float) -> dict:
    """A still recording of the unit, ``seconds`` long (the columns of ``SessionStream.chunk``)."""
    return SessionStream(model, still(), RATE_HZ, seed=10_000 + seed, boot=0).chunk(int(seconds * RATE_HZ))


def spec_from_still_log(c: dict, seconds: float) -> tuple[dict, dict]:
    """What an Allan analysis of a still recording ``c`` gives: the spec and the read-off [deg/h]."""
    rw, bi, tau_b, noise, shown = {}, {}, {}, {}, {}
    for a in "xyz":
        curve = allan_curve(c[f"w{a}"], RATE_HZ, max_tau_s=seconds / 10)
        t = fit_noise_terms(curve)                   # joint fit: the walk is not read off the floor
        rw[a], bi[a] = float(t.rate_random_walk.value), float(t.bias_instability.value)
        tau_b[a] = float(curve.tau_s[int(np.argmin(curve.adev))])
        noise[a] = float(t.arw.value * np.sqrt(RATE_HZ))
        shown[a] = {"arw_deg_per_sqrt_h": t.arw.value * 60, "bias_instability_dph": bi[a] * 3600,
                    "rrw_dph_per_sqrt_h": rw[a] * 3600 * 60, "floor_tau_s": tau_b[a]}
    spec = {"random_walk": {"dps_per_sqrt_s": rw},
            "bias_instability": {"dps": bi, "tau_s": float(np.mean(list(tau_b.values())))},
            "noise_dps": noise}
    return spec, shown


def spec_from_analyze(c: dict, seed: int) -> tuple[dict, dict, list[dict]]:
    """What ``gyrocal analyze`` writes for the daemon from the same still recording: its findings'
    bias blocks (``extend.bias_spec``, the part of OUT.terms.yaml that ``BiasModel.from_spec`` reads),
    the causes named with their axes, and the findings themselves, so the on-line gain is measured
    through the real analysis path."""
    from gyrocal.analysis.engine import analyze
    from gyrocal.analysis.extend import bias_spec
    from gyrocal.logformat import LogData

    cols = {k: c[k] for k in ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session")}
    r = analyze(LogData(cols, {}, [], "still recording"), seed=seed).result
    return (bias_spec(r["findings"], r["allan_terms"]), {f["cause"]: f["axes"] for f in r["findings"]},
            r["findings"])


def reml_walk_spec(analyzed: dict, findings: list[dict]) -> dict | None:
    """The analyze spec with its walk taken from the walk test's REML intensity (the finding's
    ``dps_per_sqrt_s``) in place of the joint Allan fit's K: the alternative docs/analysis.md left
    unmeasured ("The walk's intensity in the finding"). None when analyze named no walk."""
    rw = next((f for f in findings if f["cause"] == "random_walk"), None)
    if rw is None or "random_walk" not in analyzed:
        return None
    out = json.loads(json.dumps(analyzed))
    out["random_walk"]["dps_per_sqrt_s"] = {a: float(v) for a, v in rw["params"]["dps_per_sqrt_s"].items()}
    return out


def true_bias(model: TruthModel) -> BiasModel:
    e = model.effects
    mid = float(np.sqrt(FLICKER_BAND_S[0] * FLICKER_BAND_S[1]))
    return BiasModel.from_spec({"random_walk": {"dps_per_sqrt_s": e.random_walk_dps_per_sqrt_s.tolist()},
                                "bias_instability": {"dps": e.bias_instability_dps.tolist(), "tau_s": mid},
                                "noise_dps": [model.noise_dps] * 3})


def _terms(cols: dict) -> np.ndarray:
    return SPEC.design({"gx": cols["gx"], "gy": cols["gy"], "gz": cols["gz"]})


def run_one(model: TruthModel, seed: int, session_s: float, after_s: float, spec: dict,
            analyzed: dict | None = None, reml: dict | None = None) -> dict:
    """One session per method on the same stream; the drift left after each method's push [deg/h]."""
    ests = {
        "rls": make_estimator("rls"),
        "rls_forget": make_estimator("rls", forgetting=0.9999),
        "kf_spec": make_estimator("kf", bias=BiasModel.from_spec(spec, "allan read-off"), dt_s=1 / RATE_HZ,
                                  horizon_s=after_s),
    }
    if analyzed is not None:
        ests["kf_analyze"] = make_estimator("kf", bias=BiasModel.from_spec(analyzed, "analyze spec"),
                                            dt_s=1 / RATE_HZ, horizon_s=after_s)
    if reml is not None:
        ests["kf_analyze_reml"] = make_estimator(
            "kf", bias=BiasModel.from_spec(reml, "analyze spec, REML walk"), dt_s=1 / RATE_HZ,
            horizon_s=after_s)
    ests |= {
        "kf_true": make_estimator("kf", bias=true_bias(model), dt_s=1 / RATE_HZ, horizon_s=after_s),
    }
    cpu = dict.fromkeys(ests, 0.0)
    stream = SessionStream(model, tumble(), RATE_HZ, seed=seed, boot=0)
    chunk = int(RATE_HZ)
    for _ in range(int(session_s)):
        c = stream.chunk(chunk)
        st = c["still"].astype(bool)
        if not st.any():
            continue
        phi = _terms(c)[st]
        y = np.column_stack([c[f"w{a}"] for a in "xyz"])[st]
        for name, est in ests.items():
            t0 = time.process_time()
            est.update_many(phi, y, c["t"][st])
            cpu[name] += time.process_time() - t0
    pushed = {name: est.coefficients for name, est in ests.items()}
    truth = model.coeffs_dps.copy()
    truth[:, 0] += stream.bias_dps
    c = stream.chunk(int(after_s * RATE_HZ))
    st = c["still"].astype(bool)
    phi = _terms(c)[st]
    drift = np.column_stack([c[f"drift_w{a}"] for a in "xyz"])[st]
    dwell = segment_ids(st)[st]
    n_dwell = np.bincount(dwell)
    first = np.bincount(dwell, weights=(c["t"][st] - c["t"][0]) < tumble().cycle_s) > 0
    def dwell_means(left: np.ndarray) -> np.ndarray:
        return np.column_stack([np.bincount(dwell, weights=left[:, k]) / n_dwell for k in range(3)])

    # the floor: the wander's own change within the window (what even the best constant, chosen
    # knowing the future, leaves); a push can only remove what lies above it
    wander = dwell_means(drift - phi @ truth.T)
    w0 = wander[first] - wander[first].mean(axis=0)
    out = {"floor": {"at_push_dph": float(np.sqrt(np.mean(w0**2)) * 3600),
                     "after_dph": float(np.sqrt(np.mean((wander - wander.mean(axis=0)) ** 2)) * 3600),
                     "samples_per_cpu_s": None}}
    for name, coef in pushed.items():
        left = drift - phi @ coef.T
        # the drift left per dwell (its mean over the 1.5 s rest): what a drift figure in deg/h means
        mean = dwell_means(left)
        out[name] = {"at_push_dph": float(np.sqrt(np.mean(mean[first] ** 2)) * 3600),
                     "after_dph": float(np.sqrt(np.mean(mean**2)) * 3600),
                     "samples_per_cpu_s": float(ests[name].samples / max(cpu[name], 1e-9))
                     if name in ests else None}
    return out


def run_daemon(method: str, model_case: str, seed: int, after_s: float, work: Path, spec: dict,
               timeout_s: float = 1500.0) -> dict:
    """End to end: ``gyrocal run`` on a virtual unit with the case's noise (``gyrocal sim --noise``),
    until its first push is acked plus ``after_s``; the drift left is read from the unit's truth record
    (drift_w - comp_w, what the unit really subtracted), dwell means after the push [deg/h]."""
    import os
    import subprocess

    import yaml

    work.mkdir(parents=True, exist_ok=True)
    c = CASES[model_case]
    rec = work / "unit.csv"
    band = f"{FLICKER_BAND_S[0]},{FLICKER_BAND_S[1]}"
    noise = ["--noise", f"noise_dps={NOISE_DPS}", "--noise", f"flicker_band_s={band}",
             "--noise", f"random_walk_dps_per_sqrt_s={c['random_walk_dps_per_sqrt_s']}",
             "--noise", f"bias_instability_dps={c['bias_instability_dps']}"]
    terms: object = "seed000"
    if method == "kf":
        (work / "spec.terms.yaml").write_text(yaml.safe_dump({"terms": list(SEED000_TERMS), **spec}),
                                              encoding="utf-8")
        terms = "spec.terms.yaml"
    cfg = {"virtual_unit": {"enabled": True, "rate_hz": RATE_HZ, "seed": seed,
                            "extra_args": [*noise, "--record", str(rec)]},
           # this unit's noise (0.05 deg/s per sample) needs ~100,000 rest samples for 1e-3 deg/s
           "estimator": {"method": method, "terms": terms,
                         "convergence": {"max_change_dps": 5e-3, "max_sigma_dps": 2e-3, "window": 5000}},
           "state_dir": str(work / "state"), "control_socket": str(work / "control.sock")}
    (work / "config.yaml").write_text(yaml.safe_dump(cfg), encoding="utf-8")
    cli = [sys.executable, "-m", "gyrocal.cli"]
    log = open(work / "daemon.log", "w")  # noqa: SIM115 (closed below)
    proc = subprocess.Popen([*cli, "run", "--config", str(work / "config.yaml")], stdout=subprocess.DEVNULL,
                            stderr=log, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    pushed_at = None
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < timeout_s and proc.poll() is None:
            time.sleep(5.0)
            r = subprocess.run([*cli, "status", "--json", "--socket", str(work / "control.sock")],
                               capture_output=True, text=True, timeout=30)
            st = json.loads(r.stdout) if r.returncode == 0 and r.stdout.strip() else {}
            if pushed_at is None and (st.get("last_push") or {}).get("status") == "acked":
                pushed_at = time.monotonic()
            if pushed_at is not None and time.monotonic() - pushed_at >= after_s:
                break
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
    truth_csv = work / "unit.truth.csv"
    with truth_csv.open(encoding="utf-8") as f:  # "# key: value" lines, then the header row
        skip = sum(1 for _ in iter(lambda: f.readline().startswith("#"), False))
    d = np.genfromtxt(truth_csv, delimiter=",", names=True, skip_header=skip)
    comp = np.column_stack([d[f"comp_w{a}"] for a in "xyz"])
    drift = np.column_stack([d[f"drift_w{a}"] for a in "xyz"])
    changed = np.flatnonzero(np.any(comp != comp[0], axis=1))

    still_ = d["still"] > 0.5
    # the window judged: after the push, or (none) the run's last after_s, as the unit kept it
    start = int(changed[0]) if changed.size else int(np.searchsorted(d["t"], d["t"][-1] - after_s))
    window = np.arange(d.size) >= start
    row = {"pushed": pushed_at is not None, "applied": bool(changed.size), "wall_s": time.monotonic() - t0,
           "window_t_s": [float(d["t"][start]), float(d["t"][-1])],
           "after_dph": dwell_rms_dph(window & still_, drift - comp),  # what the unit kept, compensated
           "uncompensated_dph": dwell_rms_dph(window & still_, drift)}  # the same rests, no set at all
    if changed.size:
        row["push_t_s"] = float(d["t"][changed[0]])
    return row


def dwell_rms_dph(still_mask: np.ndarray, left_dps: np.ndarray) -> float:
    """RMS over the still dwells (runs of ``still_mask``) of each dwell's mean of ``left_dps`` (N, 3)
    [deg/s], in deg/h: what a drift figure means to a navigation user (the mean over a rest)."""
    if not np.any(still_mask):
        return float("nan")
    dwell = segment_ids(still_mask)[still_mask]
    n = np.bincount(dwell)
    mean = np.column_stack([np.bincount(dwell, weights=left_dps[still_mask, k]) / n for k in range(3)])
    return float(np.sqrt(np.mean(mean**2)) * 3600)


def paired_ratio(method: list[float], rls: list[float]) -> dict | None:
    """Per seed method / rls on the same stream: the geometric mean of the ratios with its 95 % t
    interval, and on how many seeds the method left less. Paired, because the seed-to-seed spread of
    the drift left (11-19 deg/h) is larger than the methods' difference."""
    from scipy import stats

    r = np.log(np.asarray(method) / np.asarray(rls))
    if r.size < 2:
        return None
    half = float(stats.t.ppf(0.975, r.size - 1) * r.std(ddof=1) / np.sqrt(r.size))
    return {"ratio": float(np.exp(r.mean())), "lo": float(np.exp(r.mean() - half)),
            "hi": float(np.exp(r.mean() + half)), "better": int(np.sum(r < 0)), "seeds": int(r.size)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    ap.add_argument("--quick", action="store_true", help="2 seeds, 600 s sessions, 2 cases (~1 min)")
    ap.add_argument("--seeds", type=int, default=6, help="sessions per case (default 6)")
    ap.add_argument("--session", type=float, default=1800.0, metavar="S", help="calibration session [s]")
    ap.add_argument("--after", type=float, default=600.0, metavar="S", help="window after the push [s]")
    ap.add_argument("--still-log", type=float, default=14400.0, metavar="S",
                    help="length of the still recording the spec is read from [s] (default 14400)")
    ap.add_argument("--no-analyze", action="store_true",
                    help="leave out kf_analyze (the spec `gyrocal analyze` writes from the still log)")
    ap.add_argument("--reml-walk", action="store_true",
                    help="add kf_analyze_reml: the analyze spec with the walk test's REML intensity in "
                    "place of the joint Allan fit's K")
    ap.add_argument("--daemon", action="store_true",
                    help="end to end: the daemon with rls and with kf (the spec analyze writes; with "
                    "--no-analyze the benchmark's own Allan fit) on a walk+flicker virtual unit")
    ap.add_argument("--work", default="out/bench_bias_state", help="work directory of --daemon")
    ap.add_argument("--methods", default="rls,kf", help="--daemon: methods to run (default rls,kf)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"cases to run (default {','.join(CASES)})")
    args = ap.parse_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so a stopped run stops its daemon too
    if args.daemon:
        model = unit("walk+flicker")
        still_s = 3600.0 if args.quick else args.still_log
        # kf gets what a user would give it: the spec `gyrocal analyze` writes from the still log
        rec = still_recording(model, 0, still_s)
        spec = spec_from_still_log(rec, still_s)[0] if args.no_analyze else spec_from_analyze(rec, 0)[0]
        seeds = range(1 if args.quick else min(args.seeds, 3))
        out: dict = {"case": "walk+flicker", "after_s": args.after, "spec": spec, "runs": {}}
        for s in seeds:
            for method in args.methods.split(","):
                work = Path(args.work) / f"{method}-{s}"
                r = run_daemon(method, "walk+flicker", s + 1, args.after, work, spec)
                out["runs"][f"{method}-seed{s + 1}"] = r
                if not args.json:
                    print(method, s + 1, r, flush=True)
        print(json.dumps(out, indent=1) if args.json else "")
        return 0
    cases = [c for c in args.cases.split(",") if c]
    if any(c not in CASES for c in cases):
        ap.error(f"--cases: choose from {', '.join(CASES)}")
    if args.quick:
        args.seeds, args.session, args.after, args.still_log = 2, 600.0, 300.0, 3600.0
        cases = ["walk+flicker", "none"]
    res: dict = {"rate_hz": RATE_HZ, "noise_dps": NOISE_DPS, "session_s": args.session, "after_s": args.after,
                 "seeds": args.seeds, "cases": {}}
    for case in cases:
        model = unit(case)
        rec = still_recording(model, 0, args.still_log)  # one recording for both specs
        spec, shown = spec_from_still_log(rec, args.still_log)
        analyzed, named, findings = (None, None, []) if args.no_analyze else spec_from_analyze(rec, 0)
        reml = reml_walk_spec(analyzed, findings) if args.reml_walk and analyzed is not None else None
        runs = [run_one(model, s, args.session, args.after, spec, analyzed, reml) for s in range(args.seeds)]
        summary: dict = {"truth": CASES[case], "allan_read_off": shown, "spec": spec, "methods": {}}
        if analyzed is not None:
            summary |= {"analyze_findings": named, "analyze_spec": analyzed}
        if reml is not None:
            summary["analyze_spec_reml_walk"] = reml
        for name in runs[0]:
            at = np.array([r[name]["at_push_dph"] for r in runs])
            af = np.array([r[name]["after_dph"] for r in runs])
            summary["methods"][name] = {
                "at_push_dph_mean": float(at.mean()), "at_push_dph_per_seed": np.round(at, 3).tolist(),
                "after_dph_mean": float(af.mean()), "after_dph_per_seed": np.round(af, 3).tolist(),
                "samples_per_cpu_s": None if runs[0][name]["samples_per_cpu_s"] is None
                else float(np.mean([r[name]["samples_per_cpu_s"] for r in runs])),
            }
        base, floor = summary["methods"]["rls"], summary["methods"]["floor"]
        for m in summary["methods"].values():
            for key in ("at_push", "after"):
                m[f"{key}_vs_rls"] = m[f"{key}_dph_mean"] / base[f"{key}_dph_mean"]
                # above the floor (quadrature): the part a push can remove
                m[f"{key}_excess_dph"] = float(np.sqrt(max(m[f"{key}_dph_mean"] ** 2
                                                           - floor[f"{key}_dph_mean"] ** 2, 0.0)))
        for name, m in summary["methods"].items():
            m["after_excess_vs_rls"] = m["after_excess_dph"] / max(base["after_excess_dph"], 1e-12)
            for key in ("at_push", "after"):
                per_seed = f"{key}_dph_per_seed"
                m[f"{key}_paired_vs_rls"] = (paired_ratio(m[per_seed], base[per_seed])
                                             if name not in ("rls", "floor") else None)
        res["cases"][case] = summary
        if not args.json:
            print(f"\n{case}: truth {CASES[case]}, spec from a {args.still_log:.0f} s still log")
            if analyzed is not None:
                print(f"analyze names {named}; its bias blocks {json.dumps(analyzed)}")
            print(f"{'method':<12} {'at push deg/h':>14} {'x rls':>7} {f'next {args.after:.0f}s deg/h':>16} "
                  f"{'x rls':>7} {'above floor':>12} {'x rls':>7} {'samples/cpu-s':>14}")
            for name, m in summary["methods"].items():
                rate = m["samples_per_cpu_s"] or 0
                print(f"{name:<12} {m['at_push_dph_mean']:>14.3f} {m['at_push_vs_rls']:>7.2f} "
                      f"{m['after_dph_mean']:>16.3f} {m['after_vs_rls']:>7.2f} "
                      f"{m['after_excess_dph']:>12.3f} {m['after_excess_vs_rls']:>7.2f} {rate:>14.0f}")
            for name, m in summary["methods"].items():
                for key in ("at_push", "after"):
                    pr = m[f"{key}_paired_vs_rls"]
                    if pr:
                        print(f"{name} / rls, {key}, paired: {pr['ratio']:.3f} [{pr['lo']:.3f}, "
                              f"{pr['hi']:.3f}], less on {pr['better']} of {pr['seeds']} seeds")
    if args.json:
        print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
