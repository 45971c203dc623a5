"""``gyrocal fit LOG.csv --method {lms,nlms,rls,batch} [--terms ...] [--all-samples] --json`` (Contract 3).

- rls, nlms: one pass over the samples in time order, as the daemon learns on line;
- batch: seed 000 eq. (4), rank-aware;
- lms: seed 000's training: epochs over the input/output pairs with alpha 0.95 -> 0.4 from random
  weights in (-1, 1) (seeded). The pairs are the means of the still periods, as the seed's static
  drift data (one pair per rest), or every sample with ``--all-samples``.

Uncertainty, identifiability and the residual RMS come from the same least-squares statistics for
every method. An undetermined coefficient has uncertainty ``null`` in the JSON (+inf).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import yaml

from gyrocal.errors import ConfigError
from gyrocal.logformat import AXES, read_log
from gyrocal.model.methods import LMS, METHODS, make_estimator
from gyrocal.model.normalise import Normaliser
from gyrocal.model.prep import prepare
from gyrocal.model.terms import SEED000_TERMS, TermSpec


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="LOG.csv", help="a log in the format of DESIGN.md Contract 1")
    parser.add_argument("--method", choices=list(METHODS), default="rls", help="estimator (default rls)")
    parser.add_argument("--terms", nargs="+", metavar="TERM",
                        help="term names, e.g. 1 gx gy gz temp temp*dtemp (default: seed 000's 10 terms)")
    parser.add_argument("--terms-file", metavar="FILE.yaml", help="YAML {terms: [...]} or a plain list")
    parser.add_argument("--all-samples", action="store_true", help="use every sample, not only still periods")
    parser.add_argument("--forgetting", type=float, default=1.0, help="RLS forgetting factor (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of LMS's random initial weights")
    parser.add_argument("--json", action="store_true", help="print the Contract 3 JSON object")


def load_terms(args: argparse.Namespace) -> list[str]:
    """Term names from --terms / --terms-file (not both); seed 000's by default."""
    if args.terms and args.terms_file:
        raise ConfigError("give --terms or --terms-file, not both")
    if args.terms_file:
        path = args.terms_file
        try:
            doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError) as err:
            raise ConfigError(f"{path}: cannot read the terms file ({err})") from err
        names = doc.get("terms") if isinstance(doc, dict) else doc
        if not isinstance(names, list) or not names or not all(isinstance(n, str | int) for n in names):
            raise ConfigError(
                f"{path}: field 'terms' must be a list of term names, e.g. terms: ['1', gx, temp]")
        return [str(n) for n in names]
    if args.terms:
        return [n for arg in args.terms for n in arg.split(",") if n]
    return list(SEED000_TERMS)


def fit(log_path: str, method: str, terms: list[str], all_samples: bool = False, forgetting: float = 1.0,
        seed: int = 0) -> dict:
    """Fit a log; returns the Contract 3 object (plus 'skipped' and 'convergence')."""
    log = read_log(log_path)
    spec = TermSpec.parse(terms)
    data = prepare(log, spec, all_samples)
    if len(data.phi) == 0:
        raise ConfigError(f"{log_path}: no still samples found; try --all-samples")
    norm = Normaliser.from_data(spec, data.phi, data.y)
    kw: dict = {"normaliser": norm}
    if method == "rls":
        kw["forgetting"] = forgetting
    if method in ("lms", "nlms"):
        kw["seed"] = seed
    est = make_estimator(method, spec, **kw)
    if isinstance(est, LMS) and method == "lms":
        est.absorb(data.phi, data.y, data.t)
        pairs = (data.phi, data.y) if all_samples else data.segment_means()
        est.train_seed(*pairs)
    else:
        est.update_many(data.phi, data.y, data.t)
    coeffs, sigma, ident = est.coefficients, est.uncertainty, est.identifiability
    rms = est.residual_rms_dps

    def row(a: np.ndarray) -> list[float | None]:
        return [float(v) if math.isfinite(v) else None for v in a]

    return {
        "method": method, "terms": spec.names, "samples": est.samples,
        "coefficients": {ax: row(coeffs[i]) for i, ax in enumerate(AXES)},
        "uncertainty": {ax: row(sigma[i]) for i, ax in enumerate(AXES)},
        "identifiable": ident.as_contract(),
        "rms": {ax: float(rms[i]) for i, ax in enumerate(AXES)},
        "skipped": {k: v for k, v in est.counts.items() if k != "accepted"},
        "rows": data.total_rows, "still_only": not all_samples,
    }


def format_table(res: dict) -> str:
    """A readable table: one row per term, value +- 1-sigma per axis [deg/h per term unit]."""
    lines = [f"method {res['method']}, {res['samples']} of {res['rows']} samples "
             f"({'still periods' if res['still_only'] else 'all samples'}); "
             "coefficients in deg/h per term unit",
             f"{'term':<14}" + "".join(f"{'axis ' + ax:>24}" for ax in AXES)]
    for j, name in enumerate(res["terms"]):
        cells = []
        for ax in AXES:
            c, s = res["coefficients"][ax][j], res["uncertainty"][ax][j]
            cells.append(f"{c * 3600:>11.3f} +- " + (f"{s * 3600:<9.3f}" if s is not None else "undeterm."))
        lines.append(f"{name:<14}" + "".join(f"{c:>24}" for c in cells))
    ident = res["identifiable"]
    und = ident["undetermined"]
    lines.append(f"rank {ident['rank']} of {len(res['terms'])}"
                 + ("; undetermined (= 0 on the data): " + "; ".join(und) if und else ""))
    lines.append("residual rms [deg/s]: " + ", ".join(f"{ax} {res['rms'][ax]:.4g}" for ax in AXES))
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    res = fit(args.log, args.method, load_terms(args), args.all_samples, args.forgetting, args.seed)
    print(json.dumps(res) if args.json else format_table(res))
    return 0
