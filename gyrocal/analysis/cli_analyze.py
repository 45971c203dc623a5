"""``gyrocal analyze LOG --json OUT.json [--report DIR]``: what the simulation gets wrong.

LOG is any format of docs/logformat.md; what the reader dropped is said on stderr and in the
JSON's ``input`` object (rows in the source, rows used, dropped by reason, warnings).

Exits 0 whenever the analysis ran, whatever it found. Progress goes to stderr (the JSON may go to
stdout with ``--json -``). The extended model spec is written next to the JSON as
``OUT.terms.yaml`` (or to ``--spec PATH``), ready for ``gyrocal fit --terms-file``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from gyrocal.analysis.engine import analyze
from gyrocal.analysis.extend import write_spec
from gyrocal.errors import GyrocalError
from gyrocal.model.cli_fit import no_data_error
from gyrocal.model.still import missing_samples
from gyrocal.readers import accounting, add_arguments, read_from_args


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="a log: CSV, .asc/.blf, .ulg, .bin, .tlog, ... (docs/logformat.md)")
    parser.add_argument("--json", metavar="OUT.json", help="write the result here ('-' = stdout)")
    parser.add_argument("--report", metavar="DIR", help="write report.md and PNG plots into DIR")
    parser.add_argument("--spec", metavar="PATH", help="where to write the extended model spec (YAML)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated noise (default 0)")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")
    add_arguments(parser)


def _clean(x):
    """JSON-safe: NaN/Inf become null (strict JSON readers reject NaN)."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def main(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()

    def say(msg: str) -> None:
        if not args.quiet:
            print(f"analyze [{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    log = read_from_args(args.log, args)
    if len(log) and "t" in log.columns and "session" in log.columns:
        missing = missing_samples(np.asarray(log["t"], dtype=float),
                                  np.asarray(log["session"], dtype=float))
        if missing:  # a regular clock with rows missing: the rate counts them (model/still.py)
            log.warnings.append(f"{missing} samples are missing from a regular clock (intervals of 2 or "
                                "more sample periods); the rate counts them, and the Allan curve closes "
                                "the gaps")
    for w in log.warnings:
        print(f"gyrocal: warning: {w}", file=sys.stderr)
    if log.dropped:
        first = f" (first at line {log.skipped_rows[0]})" if log.skipped_rows else ""
        say("dropped " + ", ".join(f"{v} {k}" for k, v in log.dropped.items()) + first)
    if len(log) == 0:
        raise no_data_error(log, args.log)
    res = analyze(log, progress=say, seed=args.seed)
    out = _clean(res.result)
    out["input"] = accounting(log)
    spec_path = args.spec or (str(Path(args.json).with_suffix(".terms.yaml"))
                              if args.json and args.json != "-" else None)
    if spec_path:
        write_spec(spec_path, out, args.log)
        out["extended"]["spec_file"] = str(spec_path)
    # the result first: a report that fails (a full disk, a plot) must not lose minutes of analysis
    text = json.dumps(out, indent=1)
    if args.json == "-":
        print(text)
    elif args.json:
        Path(args.json).write_text(text + "\n", encoding="utf-8")
    if args.report:
        from gyrocal.analysis.report import write_report  # matplotlib only when asked

        try:
            write_report(args.report, res, out, args.log)
        except OSError as err:
            raise GyrocalError(f"--report {args.report}: cannot write the report ({err})") from err
        say(f"report written to {args.report}/report.md")
    if not args.json:
        _summary(out)
    say(f"done: {len(out['findings'])} finding(s)")
    return 0


def _summary(out: dict) -> None:
    """A short human summary on stdout when no JSON file was asked for."""
    if not out["findings"]:
        print("nothing significant beyond gravity-dependent drift and white noise")
    for f in out["findings"]:
        head = f"{f['cause']}: axes {','.join(f['axes'])}"
        if f.get("p_value") is None:  # a noise cause (coloured_noise, bias_instability): valued by fidelity
            gain = (f.get("params") or {}).get("fidelity_gain_decades") or {}  # per axis (noisecauses.py)
            print(head + (f", fidelity gain {max(gain.values()):.2f} decades" if gain else ""))
        else:
            print(f"{head}, explains {f.get('explained_fraction') or 0.0:.1%} (p={f['p_value']:.2g})")
    g = out["gain"]
    print(f"gain (tau_s={out['tau_s']:g}): " + ", ".join(f"{a}={g[a]:.2f}" for a in g if g[a] is not None))
