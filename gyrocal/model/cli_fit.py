"""``gyrocal fit LOG --method {lms,nlms,rls,batch} [--terms ...] [--all-samples] --json``.

LOG is any format of docs/logformat.md (CSV, python-can logs, serial captures, .ulg, .bin, .tlog, rosbag2).

- rls, nlms: one pass over the samples in time order, as the daemon learns on line;
- batch: seed 000 eq. (4), rank-aware;
- lms: seed 000's training: epochs over the input/output pairs with alpha 0.95 -> 0.4 from random
  weights in (-1, 1) (seeded). The pairs are the means of the still periods, as the seed's static
  drift data (one pair per rest), or every sample with ``--all-samples``.

Uncertainty, and what it means per method (``uncertainty_kind`` in the JSON):

- batch, rls: ``ls_1sigma``, the least-squares 1-sigma from the residual (RLS with forgetting 1
  is the least-squares solution; with forgetting < 1 it is the sigma of the weighted problem).
- kf: ``kalman_posterior_1sigma``, from the filter's covariance (model/bias_kalman.py).
- lms, nlms: ``ls_1sigma_plus_offset``. These gradient methods stop short of the least-squares
  solution c_ls, and the LS sigma alone says nothing about that: on a tumble log NLMS sat ~37
  sigma away from batch while printing batch's sigma. Their error is (c - c_ls) + (c_ls - truth),
  the first part known from the data, the second of size sigma_ls, so we report
  sqrt((c - c_ls)^2 + sigma_ls^2) and, in ``offset_from_ls_sigma``, |c - c_ls| / sigma_ls.

An undetermined coefficient has uncertainty ``null`` in the JSON (+inf). Every row the reader or
the fit left out is counted in ``skipped`` by reason (``nonfinite``, ``not_still``, ...).
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from gyrocal.errors import ConfigError
from gyrocal.logformat import AXES, LogData
from gyrocal.model.methods import LMS, METHODS, make_estimator
from gyrocal.model.normalise import Normaliser
from gyrocal.model.prep import prepare
from gyrocal.model.terms import SEED000_TERMS, TermSpec, read_terms_file
from gyrocal.protocol import termsets
from gyrocal.readers import ReadOptions, accounting, add_arguments, read_any, read_from_args
from gyrocal.replay.source import applied_from_metadata


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="LOG",
                        help="CSV, python-can log, serial capture, .ulg, .bin, .tlog, rosbag2 "
                             "(docs/logformat.md)")
    parser.add_argument("--method", choices=list(METHODS), default="rls", help="estimator (default rls)")
    parser.add_argument("--terms", nargs="+", metavar="TERM",
                        help="term names, e.g. 1 gx gy gz temp temp*dtemp (default: seed 000's 10 terms)")
    parser.add_argument("--terms-file", metavar="FILE.yaml", help="YAML {terms: [...]} or a plain list")
    parser.add_argument("--all-samples", action="store_true", help="use every sample, not only still periods")
    parser.add_argument("--forgetting", type=float, default=1.0, help="RLS forgetting factor (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of LMS's random initial weights")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    add_arguments(parser)


def load_terms(args: argparse.Namespace) -> list[str]:
    """Term names from --terms / --terms-file (not both); seed 000's by default."""
    if args.terms and args.terms_file:
        raise ConfigError("give --terms or --terms-file, not both")
    if args.terms_file:
        return read_terms_file(args.terms_file)
    if args.terms:
        return [n for arg in args.terms for n in arg.split(",") if n]
    return list(SEED000_TERMS)


def no_data_error(log: LogData, name: str) -> ConfigError:
    """The real reason a log gave no usable rows: empty, header only, or every row dropped (and why)."""
    if log.data_rows == 0:
        if not log.dropped:
            return ConfigError(f"{name}: the log holds no data rows (only a header or metadata)")
        why = ", ".join(f"{v} {k}" for k, v in log.dropped.items())
        return ConfigError(f"{name}: no sample could be decoded ({why}); is it the format its "
                           "extension says? (--format, docs/logformat.md)")
    why = ", ".join(f"{v} {k}" for k, v in log.dropped.items()) or "no reason recorded"
    return ConfigError(f"{name}: all {log.data_rows} data rows were dropped ({why}); "
                       "nothing is left to fit (docs/logformat.md)")


def applied_set(log: LogData, where: str) -> tuple[tuple[list[str], np.ndarray] | None, str | None]:
    """The set the logged unit held (the ``applied_*`` metadata the CAN and serial readers write), to
    be added back to its compensated output, and the warning that says so; (None, None) without one.

    Why: fitted as recorded, a log of a unit holding v3 gave what is left after v3, with no word, and
    `push --file` of that output would have replaced v3 by its small remainder (an audit with foreign
    recordings)."""
    rep = applied_from_metadata(log.metadata, where)
    if rep is None or rep.version == 0 and not np.any(np.asarray(rep.coeffs_dps, dtype=np.float64)):
        return None, None
    names = termsets.names_for(rep.terms_id)
    if names is None:
        return None, (f"the logged unit held v{rep.version}, terms id 0x{rep.terms_id:04x}, which this "
                      "tool does not know: fitted as recorded, i.e. what is left after that set, not a "
                      "whole set to push")
    return (list(names), np.asarray(rep.coeffs_dps, dtype=np.float64)), (
        f"the logged unit held v{rep.version} ({len(names)} terms): its output is compensated with it, so "
        "that set was added back and the fit is of the whole drift (a set to push as it is)")


def fit(log_path: str, method: str, terms: list[str], all_samples: bool = False, forgetting: float = 1.0,
        seed: int = 0, log: LogData | None = None, read: ReadOptions | None = None) -> dict:
    """Fit a log; returns the fit object (coefficients, uncertainty and its kind, skipped rows)."""
    if log is None:
        log = read_any(log_path, None, read)
    if len(log) == 0:
        raise no_data_error(log, log_path)
    spec = TermSpec.parse(terms)
    applied, note = applied_set(log, log_path)
    warnings = list(log.warnings) + ([note] if note else [])
    try:
        data = prepare(log, spec, all_samples, applied=applied)
    except ConfigError as err:  # a term needs a column this log lacks: say which log
        raise ConfigError(f"{log_path}: {err}") from None
    if len(data.phi) == 0:
        raise ConfigError(f"{log_path}: none of its {len(log)} rows lies in a still period; "
                          "add --all-samples to fit every sample")
    sessions = int(np.unique(log["session"]).size) if log.has("session") else 1
    # time restarts at each switch-on: the estimator's time check dropped every session after the
    # first as time_backwards (17,166 of 19,000 rows of an outside user's CAN log with a power cycle:
    # rc36b M2). Each reader keeps time in order within a session, so across several none is checked.
    t_fit = data.t if sessions == 1 else None
    if sessions > 1:
        warnings.append(f"{sessions} sessions (switch-ons): every one is fitted, with one set of "
                        "coefficients; the bias changes at each switch-on, so the constant is their "
                        "mean (docs/logformat.md)")
    norm = Normaliser.from_data(spec, data.phi, data.y)
    kw: dict = {"normaliser": norm}
    if method == "rls":
        kw["forgetting"] = forgetting
    if method in ("lms", "nlms"):
        kw["seed"] = seed
    est = make_estimator(method, spec, **kw)
    if isinstance(est, LMS) and method == "lms":
        est.absorb(data.phi, data.y, t_fit)
        pairs = (data.phi, data.y) if all_samples else data.segment_means()
        est.train_seed(*pairs)
    else:
        est.update_many(data.phi, data.y, t_fit)
    coeffs, sigma, ident = est.coefficients, est.uncertainty, est.identifiability
    rms = est.residual_rms_dps
    kind, offset = ("kalman_posterior_1sigma" if method == "kf" else "ls_1sigma"), None
    if method in ("lms", "nlms"):
        ls = make_estimator("batch", spec, normaliser=norm)
        ls.update_many(data.phi, data.y, t_fit)
        d = coeffs - ls.coefficients
        with np.errstate(invalid="ignore", divide="ignore"):
            offset = np.where(np.isfinite(sigma), np.abs(d) / sigma, np.nan)
        sigma = np.where(np.isfinite(sigma), np.sqrt(d * d + sigma * sigma), sigma)
        kind = "ls_1sigma_plus_offset"

    def row(a: np.ndarray) -> list[float | None]:
        return [float(v) if math.isfinite(v) else None for v in a]

    skipped = dict(log.dropped)
    for k, v in est.counts.items():
        if k != "accepted":
            skipped[k] = skipped.get(k, 0) + int(v)
    skipped["not_still"] = 0 if all_samples else len(log) - len(data.phi)
    out = {
        "method": method, "terms": spec.names, "samples": est.samples,
        "coefficients": {ax: row(coeffs[i]) for i, ax in enumerate(AXES)},
        "uncertainty": {ax: row(sigma[i]) for i, ax in enumerate(AXES)},
        "uncertainty_kind": kind,
        "identifiable": ident.as_contract(),
        "rms": {ax: float(rms[i]) for i, ax in enumerate(AXES)},
        "skipped": skipped,
        "rows": data.total_rows, "source_rows": accounting(log)["source_rows"], "still_only": not all_samples,
        "warnings": warnings,
    }
    if "temp" in spec.names and len(data.phi):  # the range the set was fitted over: an autopilot's
        t = data.phi[:, spec.names.index("temp")]  # TMIN..TMAX when it is pushed (push --file)
        out["temp_range_c"] = [float(np.min(t)), float(np.max(t))]
    if applied is not None:
        out["applied_added"] = {"version": int(log.metadata.get("applied_version", "0")),
                                "terms": list(applied[0])}
    if offset is not None:
        out["offset_from_ls_sigma"] = {ax: row(offset[i]) for i, ax in enumerate(AXES)}
    return out


UNCERTAINTY_LABEL = {
    "ls_1sigma": "+- least-squares 1-sigma",
    "kalman_posterior_1sigma": "+- the Kalman filter's posterior 1-sigma",
    "ls_1sigma_plus_offset": "+- sqrt(offset from least squares^2 + LS sigma^2)",
}


def format_table(res: dict) -> str:
    """A readable table: one row per term, value +- 1-sigma per axis [deg/h per term unit]."""
    lines = [f"method {res['method']}, {res['samples']} of {res['rows']} samples "
             f"({'still periods' if res['still_only'] else 'all samples'}); "
             "coefficients in deg/h per term unit, "
             + UNCERTAINTY_LABEL.get(res.get("uncertainty_kind", ""), "+- 1-sigma"),
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
    off = res.get("offset_from_ls_sigma")
    if off:
        worst = max((v for ax in AXES for v in off[ax] if v is not None), default=0.0)
        lines.append(f"{res['method']} stops {worst:.1f} LS-sigma from the least-squares solution at most "
                     "(offset_from_ls_sigma in --json)")
    lines.append(skipped_line(res["source_rows"], res["skipped"]))
    return "\n".join(lines)


def skipped_line(source_rows: int, skipped: dict[str, int]) -> str:
    """``rows: 7250 in the log; not used: 50 nonfinite, 2000 not_still`` (every reason, even 0 for NaN)."""
    parts = [f"{v} {k}" for k, v in skipped.items() if v or k == "nonfinite"]
    return f"rows: {source_rows} in the log; not used: " + (", ".join(parts) if parts else "none")


def main(args: argparse.Namespace) -> int:
    log = read_from_args(args.log, args)
    for w in log.warnings:
        print(f"gyrocal: warning: {w}", file=sys.stderr)
    shown = len(log.warnings)
    res = fit(args.log, args.method, load_terms(args), args.all_samples, args.forgetting, args.seed, log=log)
    for w in res["warnings"][shown:]:  # the fit's own (sessions, the set the unit held)
        print(f"gyrocal: warning: {w}", file=sys.stderr)
    print(json.dumps(res) if args.json else format_table(res))
    return 0
