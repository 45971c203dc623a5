"""Estimator benchmark: throughput per method and convergence against batch least squares.

    .venv/bin/python benchmarks/bench_estimators.py [--json] [--out out/] [--samples 60000] [--seed 0]

On one simulated session (the virtual unit's truth model, seed 000 Table 1 on x, 18-pose tumble,
100 Hz, still samples only) it measures:
- per-sample ``update`` throughput and block ``update_many`` throughput per method [samples/s, 3 axes];
- the coefficient error (RMS over the 3 x 10 determined parts, deg/h) against samples for LMS,
  NLMS and RLS, one pass on line, and for batch least squares on the same prefix; plotted to
  OUT/bench_estimators.png;
- whether RLS after one pass is within 1.05x of the batch-LS coefficient error.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gyrocal.model.identifiability import determined_part  # noqa: E402
from gyrocal.model.methods import LMS, lstsq_reference, make_estimator  # noqa: E402
from gyrocal.model.normalise import Normaliser  # noqa: E402
from gyrocal.model.prep import FitData, gravity_direction, segment_ids  # noqa: E402
from gyrocal.model.terms import SEED000_TERMS, TermSpec  # noqa: E402
from gyrocal.sim.schedule import tumble  # noqa: E402
from gyrocal.sim.truth import SessionStream, TruthModel  # noqa: E402

METHODS = ("lms", "nlms", "rls", "batch")
DPH = 3600.0


def simulate(n: int, seed: int) -> dict:
    """Still samples of n simulated samples, their terms and the truth (3, 10) incl. switch-on bias."""
    spec = TermSpec.parse(SEED000_TERMS)
    model = TruthModel()
    stream = SessionStream(model, tumble(), 100.0, seed=seed, boot=0)
    cols = stream.chunk(n)
    still = cols["still"]
    g = gravity_direction(np.column_stack([cols[f"a{a}"] for a in "xyz"]))
    phi = spec.design({"gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]})[still]
    y = np.column_stack([cols[f"w{a}"] for a in "xyz"])[still]
    truth = model.coeffs_dps.copy()
    truth[:, 0] += stream.bias_dps
    return {"spec": spec, "phi": phi, "y": y, "t": cols["t"][still], "truth": truth,
            "segment": segment_ids(still)[still]}


def throughput(data: dict, repeat: int = 3) -> dict:
    """Best of ``repeat`` runs [samples/s of process CPU time, so a busy host does not skew it]."""
    phi, y, t = data["phi"], data["y"], data["t"]
    n = min(len(phi), 30000)
    out = {}
    variants = [(m, {}) for m in METHODS] + [("rls", {"block": 1})]
    for method, kw in variants:
        name = method + (" (block=1, W solved per sample)" if kw else "")
        m = n if not kw else min(n, 2000)
        per = blk = 0.0
        for _ in range(repeat):
            est = make_estimator(method, data["spec"], **kw)
            t0 = time.process_time()
            for i in range(m):
                est.update(phi[i], y[i], t[i])
            per = max(per, m / (time.process_time() - t0))
            est = make_estimator(method, data["spec"], **kw)
            t0 = time.process_time()
            est.update_many(phi[:m], y[:m], t[:m])
            blk = max(blk, m / (time.process_time() - t0))
        out[name] = {"per_sample_per_s": per, "block_per_s": blk}
    return out


def coefficient_error_dph(coeffs: np.ndarray, truth: np.ndarray, ident) -> float:
    return float(np.sqrt(np.mean(determined_part(coeffs - truth, ident) ** 2)) * DPH)


def convergence(data: dict, points: int = 25) -> dict:
    spec, phi, y, t, truth = data["spec"], data["phi"], data["y"], data["t"], data["truth"]
    n = len(phi)
    marks = np.unique(np.geomspace(200, n, points).astype(int))
    norm = Normaliser.nominal(spec)
    ests = {m: make_estimator(m, spec, normaliser=norm) for m in ("lms", "nlms", "rls")}
    curves: dict[str, list[float]] = {m: [] for m in (*ests, "batch")}
    full = make_estimator("batch", spec, normaliser=norm)
    full.update_many(phi, y, t)
    ident = full.identifiability  # one determined subspace for every point of every curve
    done = 0
    for k in marks:
        for est in ests.values():
            est.update_many(phi[done:k], y[done:k], t[done:k])
        done = k
        for m, est in ests.items():
            curves[m].append(coefficient_error_dph(est.coefficients, truth, ident))
        ref = lstsq_reference(norm, phi[:k], y[:k], ests["rls"].rank_tol)
        curves["batch"].append(coefficient_error_dph(ref, truth, ident))
    # the seed's own schedule: epochs over the still means, alpha 0.95 -> 0.4
    seed_lms = LMS(spec, normaliser=Normaliser.from_data(spec, phi, y), seed=0)
    seed_lms.absorb(phi, y, t)
    epochs = seed_lms.train_seed(*FitData(phi, y, t, data["segment"], n).segment_means())
    seed_err = coefficient_error_dph(seed_lms.coefficients, truth, ident)
    ratio = curves["rls"][-1] / curves["batch"][-1]
    return {"samples": marks.tolist(), "error_dph": curves, "seed_lms_epochs": len(epochs),
            "seed_lms_error_dph": seed_err, "rls_over_batch": ratio, "rls_within_1_05": bool(ratio <= 1.05),
            "rank": ident.rank,
            "converged": {m: e.convergence().reason for m, e in ests.items()}}


def plot(conv: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for m, style in (("lms", "-"), ("nlms", "-"), ("rls", "-"), ("batch", "--")):
        label = m if m != "batch" else "batch LS (eq. 4)"
        ax.loglog(conv["samples"], conv["error_dph"][m], style, label=label)
    ax.axhline(conv["seed_lms_error_dph"], color="grey", ls=":",
               label=f"seed LMS, {conv['seed_lms_epochs']} epochs on still means")
    ax.set_xlabel("still samples (100 Hz)")
    ax.set_ylabel("coefficient error, determined part [deg/h RMS]")
    ax.set_title("Convergence on the virtual unit (seed 000 Table 1 truth, 18-pose tumble)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    ap.add_argument("--out", default="out", help="directory of the PNG (default out/)")
    ap.add_argument("--samples", type=int, default=60000, help="simulated samples (default 60000)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    data = simulate(args.samples, args.seed)
    res = {"throughput": throughput(data), "convergence": convergence(data)}
    png = Path(args.out) / "bench_estimators.png"
    plot(res["convergence"], png)
    res["png"] = str(png)
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    print(f"{'method':<40}{'per-sample /s':>16}{'block /s':>16}")
    for name, r in res["throughput"].items():
        print(f"{name:<40}{r['per_sample_per_s']:>16,.0f}{r['block_per_s']:>16,.0f}")
    c = res["convergence"]
    print(f"\ncoefficient error after {c['samples'][-1]} still samples "
          f"(deg/h RMS, determined part, rank {c['rank']}):")
    for m, errs in c["error_dph"].items():
        print(f"  {m:<6} {errs[-1]:.3f}")
    print(f"  seed LMS ({c['seed_lms_epochs']} epochs on still means) {c['seed_lms_error_dph']:.3f}")
    verdict = "yes" if c["rls_within_1_05"] else "NO"
    print(f"RLS after one pass within 1.05x of batch LS: {verdict} (ratio {c['rls_over_batch']:.4f})")
    for m, why in c["converged"].items():
        print(f"  {m}: {why}")
    print(f"plot: {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
