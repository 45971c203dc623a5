"""`gyrocal status | recalibrate | rollback | push`: talk to a running daemon over its control socket.

These commands are thin clients: they build one request, send it with control.request, and print
the answer. They never touch the unit or the store themselves, so the daemon stays the one owner of
both. Exit status: 0 when the daemon answered ok, 1 when it answered ok=false (e.g. nothing to roll
back to), 2 on a user error (bad file, no daemon listening: the CLI prints the GyrocalError).

Requests sent (the daemon's handler answers them):
    {"cmd": "status"}
    {"cmd": "recalibrate"}
    {"cmd": "rollback", "to": VERSION or null}         # null: the acked version before the current one
    {"cmd": "push", "terms": [P names], "coefficients": [[P], [P], [P]], "source": "FILE"}
        coefficients are rows x, y, z in deg/s per unit of each term (as in the store).

`gyrocal status --watch` polls the daemon and prints one JSON line per change of its answer (like
gpsd's ``gpspipe -w``) until interrupted; if the daemon goes away it prints one ``{"ok": false,
"error": ...}`` line and keeps watching for its return.

The status answer is rendered from these keys when present (others are listed at the end, in full:
long values wrap under their column, nothing is cut):
    state, reason, message, unit {serial, boot_count, fw}, applied {version}, samples, still_samples,
    trained_samples, converged, converged_reason, rms_dps | monitor_rms_dps {x,y,z}, alarm, terms,
    coefficients_dps and uncertainty_dps ({x,y,z} or 3 rows), link {...}, ring {...}, validation {...},
    last_push {status, attempts, version, ...}; or "units": [one such object per unit].
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import yaml

from gyrocal.daemon.control import default_socket_path, request
from gyrocal.errors import ConfigError, GyrocalError, yaml_error_text

AXES = ("x", "y", "z")


def _add_socket(parser: argparse.ArgumentParser) -> None:
    default = default_socket_path()
    parser.add_argument("--socket", type=Path, default=default, metavar="PATH",
                        help=f"the daemon's control socket (default: $GYROCAL_SOCKET or {default})")


def _answer(reply: dict, ok_text: str | None = None) -> int:
    if not reply.get("ok", False):
        print(f"gyrocal: daemon refused: {reply.get('error', 'no reason given')}", file=sys.stderr)
        return 1
    if ok_text is not None:
        print(reply.get("message") or ok_text)
    return 0


# --- status --------------------------------------------------------------------------------------

def configure_status(parser: argparse.ArgumentParser) -> None:
    _add_socket(parser)
    parser.add_argument("--json", action="store_true", help="print the daemon's answer as JSON")
    parser.add_argument("--watch", action="store_true",
                        help="print one JSON line per change of the status until interrupted (as gpspipe -w)")
    parser.add_argument("--interval", type=_positive, default=1.0, metavar="S",
                        help="--watch: seconds between polls (default 1)")
    parser.add_argument("--count", type=int, default=0, metavar="N",
                        help="--watch: stop after N lines (default 0: until interrupted)")


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 0.05 <= v <= 3600:
        raise argparse.ArgumentTypeError("write an interval from 0.05 to 3600 s")
    return v


WATCH_IGNORES = frozenset({"uptime_s", "liveness", "latency_s", "ring", "samples", "still_samples",
                           "trained_samples", "link", "monitor_rms_dps", "coefficients_dps",
                           "uncertainty_dps", "rate_hz", "earth", "still", "predicted_drift_dph",
                           "converged_reason", "poses_seen", "dtemp_inexact_samples",
                           "push_blind_samples"})
"""Status keys that move with every sample: ``--watch`` prints a line when anything else changes
(state, reason, pushes, faults, the unit's set), with these as they are then."""
_REASON_FIGURE = re.compile(r"(?<![\w.])\d+(?:\.\d+)?")
"""A figure in status's reason ("no new direction learnt for 46 s", "predicted drift left 0.82
deg/h"), not a version (v8) or a name: ``--watch`` does not count its moves as a change. A cold
unit collecting gave a line every second, the seconds counter its only change (an integrator's
check, F6)."""


def _watch_key(reply: dict[str, Any]) -> str:
    """What ``--watch`` compares between polls: the answer without WATCH_IGNORES, and with the
    reason's figures masked."""
    kept = {k: v for k, v in reply.items() if k not in WATCH_IGNORES}
    if isinstance(kept.get("reason"), str):
        kept["reason"] = _REASON_FIGURE.sub("#", kept["reason"])
    return json.dumps(kept, sort_keys=True)


def watch_status(socket_path: Path, interval_s: float, count: int = 0) -> int:
    """JSON lines, one per change of the daemon's answer; a lost daemon is one error line, then
    watching resumes when it comes back. Returns 0 (after ``count`` lines, or on Ctrl-C)."""
    last: str | None = None
    printed = 0
    try:
        while True:
            try:
                reply = request(socket_path, {"cmd": "status"})
            except ConfigError:
                raise  # an unsafe socket directory: never poll it again
            except GyrocalError as err:
                reply = {"ok": False, "error": str(err)}
            line = json.dumps(reply, sort_keys=True, separators=(",", ":"))
            # a change is a change of anything but the clocks (uptime, sample age, latency), which
            # move at every poll and made every poll a line (an operator's audit)
            key = _watch_key(reply)
            if key != last:
                last = key
                sys.stdout.write(line + "\n")
                sys.stdout.flush()
                printed += 1
                if count and printed >= count:
                    return 0
            time.sleep(interval_s)
    except KeyboardInterrupt:
        return 0


def main_status(args: argparse.Namespace) -> int:
    if args.watch:
        return watch_status(args.socket, args.interval, args.count)
    if args.json:  # a script reads JSON whatever happened, with the same exit status as the text
        try:
            reply = request(args.socket, {"cmd": "status"})
        except ConfigError:
            raise  # an unsafe socket directory: the one line on stderr, as without --json
        except GyrocalError as err:
            print(json.dumps({"ok": False, "error": str(err)}, indent=2, sort_keys=True))
            return 2
        print(json.dumps(reply, indent=2, sort_keys=True))
        return 0 if reply.get("ok", False) else 1
    reply = request(args.socket, {"cmd": "status"})
    if not reply.get("ok", False):
        return _answer(reply)
    print(format_status(reply))
    return 0


def _fmt(v: Any, nested: bool = False) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, dict):
        text = ", ".join(f"{k}={_fmt(x, True)}" for k, x in v.items())
        return f"({text})" if nested else text
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x, True) for x in v) + "]"
    return str(v)


def _rows(coeffs: Any) -> list[tuple[str, list]] | None:
    if isinstance(coeffs, dict) and all(a in coeffs for a in AXES):
        return [(a, coeffs[a]) for a in AXES]
    if isinstance(coeffs, list) and len(coeffs) == 3 and all(isinstance(r, list) for r in coeffs):
        return list(zip(AXES, coeffs, strict=True))
    return None


_SHOWN = {"ok", "state", "reason", "message", "unit", "serial", "applied", "version", "samples",
          "still_samples", "trained_samples", "converged", "converged_reason", "rms_dps", "rms",
          "monitor_rms_dps", "alarm", "terms", "coefficients_dps", "coefficients", "uncertainty_dps",
          "link", "ring", "last_push", "validation", "units", "reboot_needed"}


def format_status(reply: dict, width: int | None = None) -> str:
    """A human-readable status: one block per unit, tolerant of missing or unknown keys.

    Keys sit in one column as wide as the longest key (no key is glued to its value); a long value
    wraps onto indented lines within ``width`` columns (the terminal's), never cut short."""
    width = width or shutil.get_terminal_size((100, 24)).columns
    units = reply.get("units")
    if isinstance(units, list) and units:
        blocks = [_format_unit(u, width) for u in units if isinstance(u, dict)]
        extra = [(k, _fmt(v)) for k, v in reply.items() if k not in _SHOWN]
        if extra:
            blocks.append("\n".join(_render(extra, width)))
        return "\n\n".join(blocks)
    return _format_unit(reply, width)


def _render(pairs: list[tuple[str, str]], width: int) -> list[str]:
    """Aligned ``key  value`` lines; values wrap at width under the value column."""
    col = max(len(k) for k, _ in pairs) + 2
    out = []
    for key, value in pairs:
        wrapped = textwrap.wrap(value, max(20, width - col), break_on_hyphens=False) or [""]
        out.append(f"{key:<{col}}{wrapped[0]}")
        out += [" " * col + more for more in wrapped[1:]]
    return out


def _format_unit(s: dict, width: int = 100) -> str:
    pairs: list[tuple[str, str]] = [("state", f"{s.get('state', '?')}"
                                     + (f"  ({s['reason']})" if s.get("reason") else ""))]
    if s.get("message"):
        pairs.append(("message", str(s["message"])))
    unit = s.get("unit") if isinstance(s.get("unit"), dict) else {}
    serial = unit.get("serial", s.get("serial"))
    if serial is not None:
        pairs.append(("unit", f"serial {serial}" + "".join(f", {k} {v}" for k, v in unit.items()
                                                           if k != "serial")))
    applied = s.get("applied")
    version = applied.get("version") if isinstance(applied, dict) else s.get("version")
    if "applied" in s or "version" in s:
        pairs.append(("applied", f"v{version}" if version is not None else "none"))
    if s.get("samples") is not None:
        more = [f"{k.replace('_samples', '')} {s[k]}" for k in ("still_samples", "trained_samples")
                if s.get(k) is not None]
        pairs.append(("samples", f"{s['samples']}" + (f" ({', '.join(more)})" if more else "")))
    if "converged" in s:
        pairs.append(("converged", ("yes" if s["converged"] else "no")
                      + (f" ({s['converged_reason']})" if s.get("converged_reason") else "")))
    for key in ("rms_dps", "rms", "monitor_rms_dps"):
        rms = s.get(key)
        if isinstance(rms, dict):
            pairs.append(("rms [deg/s]", "  ".join(f"{a}={_fmt(rms[a])}" for a in AXES if a in rms)))
            break
    if s.get("alarm"):
        pairs.append(("ALARM", _fmt(s["alarm"])))
    need = s.get("reboot_needed")
    if isinstance(need, dict):  # a held set the unit applies only after its next reboot (docs/mavlink.md)
        pairs.append(("REBOOT NEEDED", f"v{need.get('version')}: {need.get('why', '')}"))
    for key in ("link", "ring", "validation"):
        if isinstance(s.get(key), dict) and s[key]:
            pairs.append((key, _fmt(s[key])))
    if "last_push" in s:
        pairs.append(("last push", _fmt(s["last_push"]) if s["last_push"] else "none yet"))
    pairs += [(k, _fmt(v)) for k, v in s.items() if k not in _SHOWN]
    return "\n".join(_render(pairs, width) + _coefficient_table(s))


def _coefficient_table(s: dict) -> list[str]:
    rows = _rows(s.get("coefficients_dps", s.get("coefficients")))
    if not rows:
        return []
    unc = _rows(s.get("uncertainty_dps")) or []
    unc_by_axis = dict(unc)
    terms = s.get("terms") or []
    width = max([len(str(t)) for t in terms] + [4])
    col = 22 if unc else 12
    out = ["coefficients [deg/s per term unit]" + (" +- 1 sigma" if unc else ""),
           "  " + "term".ljust(width) + "".join(f"{a:>{col}}" for a in AXES)]
    for i in range(max(len(r) for _, r in rows)):
        name = str(terms[i]) if i < len(terms) else f"#{i}"
        cells = []
        for a, r in rows:
            cell = f"{r[i]:+.4e}" if i < len(r) and isinstance(r[i], int | float) else "?"
            u = unc_by_axis.get(a)
            if u is not None and i < len(u):
                cell += f" +-{u[i]:.1e}" if isinstance(u[i], int | float) else " +- undet."
            cells.append(f"{cell:>{col}}")
        out.append("  " + name.ljust(width) + "".join(cells))
    return out


# --- recalibrate ---------------------------------------------------------------------------------

def configure_recalibrate(parser: argparse.ArgumentParser) -> None:
    _add_socket(parser)


def main_recalibrate(args: argparse.Namespace) -> int:
    return _answer(request(args.socket, {"cmd": "recalibrate"}), "recalibration started")


# --- rollback ------------------------------------------------------------------------------------

def _version(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a version number; see `gyrocal status`") from None
    if v < 1:
        raise argparse.ArgumentTypeError("versions start at 1")
    return v


def configure_rollback(parser: argparse.ArgumentParser) -> None:
    _add_socket(parser)
    parser.add_argument("--to", type=_version, default=None, metavar="VERSION",
                        help="the stored version to push again (default: the acked one before the current)")
    _add_no_wait(parser)


def _add_no_wait(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-wait", action="store_true",
                        help=f"return once the push has started; by default wait (up to {FOLLOW_S:.0f} s) "
                             "for the unit's answer and exit 1 unless it acked")


def main_rollback(args: argparse.Namespace) -> int:
    reply = request(args.socket, {"cmd": "rollback", "to": args.to})
    rc = _answer(reply, f"rolled back to version {reply.get('version', args.to or 'previous')}")
    return rc if rc or args.no_wait else follow_push(args.socket, reply.get("version"))


FOLLOW_S = 60.0
"""[s] How long ``push`` and ``rollback`` wait for the unit's answer before leaving it to status."""


def _push_of(status: dict, version: int) -> tuple[dict | None, bool]:
    """The ``last_push`` of ``version`` in a status answer (one unit, or ``units``), and whether any
    unit is still PUSHING."""
    units = status.get("units") if isinstance(status.get("units"), list) else [status]
    found, pushing = None, False
    for u in units:
        if not isinstance(u, dict):
            continue
        pushing = pushing or u.get("state") == "PUSHING" or u.get("session_state") == "PUSHING"
        lp = u.get("last_push") or {}
        if lp.get("version") == version and lp.get("status") not in (None, "pending"):
            found = lp
    return found, pushing


def follow_push(socket_path: Path, version: Any, timeout_s: float = FOLLOW_S) -> int:
    """Wait for the unit's answer to the push the daemon just started and print it: 0 when the unit
    acked and read it back, 1 otherwise. The daemon answers a push request as soon as the push starts,
    so the command said "pushing v14" and exit 0 for a set the unit then NAKed, which only the journal
    said (protocol.md: the NAK is what the operator sees; an audit with a unit built from it)."""
    if not isinstance(version, int):
        return 0
    end, quiet = time.monotonic() + timeout_s, 0
    while time.monotonic() < end:
        try:
            st = request(socket_path, {"cmd": "status"})
        except GyrocalError as err:
            print(f"gyrocal: v{version}: the daemon's status cannot be read ({err}); see `gyrocal status`",
                  file=sys.stderr)
            return 1
        lp, pushing = _push_of(st, version)
        if lp is not None:
            status = lp.get("status")
            if status == "acked":
                print(f"v{version} acked by the unit and read back")
                return 0
            why = "; ".join(str(r) for r in (lp.get("reasons") or [])[-2:])
            again = " The daemon sends it again later (`gyrocal status`)." if lp.get("transient") else ""
            print(f"gyrocal: v{version} not taken: {status}{f' ({why})' if why else ''}.{again}",
                  file=sys.stderr)
            return 1
        quiet = 0 if pushing else quiet + 1
        if quiet >= 4:
            # not pushing, and no outcome of this version: a new session took over (the unit rebooted
            # mid-push), so whether the unit holds it is for its read-back to say. Not a success: a
            # rollback cut by a reboot exited 0 with the autopilot holding no set (an integrator's audit)
            print(f"gyrocal: v{version}: its outcome is not in the daemon's status (a new session may have "
                  "started); see `gyrocal status` for the set the unit holds", file=sys.stderr)
            return 1
        time.sleep(0.25)
    print(f"gyrocal: v{version} still pushing after {timeout_s:.0f} s; see `gyrocal status`", file=sys.stderr)
    return 1


# --- push ----------------------------------------------------------------------------------------

def configure_push(parser: argparse.ArgumentParser) -> None:
    _add_socket(parser)
    parser.add_argument("--file", type=Path, required=True, metavar="FILE",
                        help="JSON or YAML with 'terms' and 'coefficients' ({x,y,z} or 3 rows, deg/s per "
                             "term unit); `gyrocal fit --json` output and store records are accepted")
    parser.add_argument("--temp-range", metavar="LO,HI",
                        help="the temperatures [degC] the set was learnt over, written as an autopilot's "
                             "TMIN,TMAX (default: the file's temp_range_c, as fit and store records give it, "
                             "else the range the link has seen)")
    _add_no_wait(parser)


def main_push(args: argparse.Namespace) -> int:
    from gyrocal.daemon.push import parse_temp_range  # imported late: it pulls in numpy

    terms, coeffs = load_coefficient_file(args.file)
    req: dict[str, Any] = {"cmd": "push", "terms": terms, "coefficients": coeffs,
                           "source": os.fspath(args.file)}
    rng = (parse_temp_range(args.temp_range, "--temp-range") if args.temp_range
           else file_temp_range(args.file))
    if rng is not None:
        req["temp_range_c"] = list(rng)
    reply = request(args.socket, req, timeout=30.0)
    rc = _answer(reply, f"pushed {len(terms)} terms from {args.file}")
    return rc if rc or args.no_wait else follow_push(args.socket, reply.get("version"))


def file_temp_range(path: Path) -> tuple[float, float] | None:
    """The range [degC] a coefficient file says its set was learnt over: ``temp_range_c`` at its top
    (`gyrocal fit --json`) or in ``stats`` (a store record); None when it says none."""
    from gyrocal.daemon.push import parse_temp_range  # imported late: it pulls in numpy

    doc = _coefficient_doc(path)
    rng = doc.get("temp_range_c", (doc.get("stats") or {}).get("temp_range_c"))
    return None if rng is None else parse_temp_range(rng, f"{path}: field 'temp_range_c'")


def _coefficient_doc(path: Path) -> dict[str, Any]:
    """A coefficient file's object (JSON, or YAML by its suffix). Raises ConfigError."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}; fix: pass an existing .json or "
                          ".yaml file to --file") from err
    try:
        if Path(path).suffix.lower() in (".yaml", ".yml"):
            doc = yaml.safe_load(text)
        else:
            doc = json.loads(text)
    except yaml.YAMLError as err:
        raise ConfigError(f"{yaml_error_text(str(path), err)}; fix: the file must hold an object with "
                          "'terms' and 'coefficients'") from err
    except ValueError as err:
        raise ConfigError(f"{path}: not valid JSON: {err}; fix: the file must hold an object with "
                          "'terms' and 'coefficients' (name YAML files .yaml)") from err
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: top level is {type(doc).__name__}; fix: it must be an object with "
                          "'terms' and 'coefficients'")
    return doc


def load_coefficient_file(path: Path) -> tuple[list[str], list[list[float]]]:
    """Read and validate a coefficient set; return (terms, 3 rows x, y, z). Raises ConfigError."""
    doc = _coefficient_doc(path)
    terms = doc.get("terms")
    if not isinstance(terms, list) or not terms or not all(isinstance(t, str) and t.strip() for t in terms):
        raise ConfigError(f"{path}: field 'terms' must be a non-empty list of term names, e.g. "
                          "['1', 'gx', 'gy', 'gz']; got " + repr(terms)[:80])
    terms = [t.strip() for t in terms]
    from gyrocal.daemon.push import MAX_PUSH_COEFF_DPS
    from gyrocal.model.terms import TermSpec  # imported late: it pulls in numpy
    from gyrocal.protocol.termsets import UNIT_ATOMS, foreign_atoms

    try:
        TermSpec.parse(terms)
        foreign = foreign_atoms(terms)
    except ConfigError as err:
        raise ConfigError(f"{path}: field 'terms': {err}") from err
    if foreign:
        # said by the daemon before, without the file or the field, exit 1 (an integrator's check, F7)
        raise ConfigError(f"{path}: field 'terms': {', '.join(map(repr, foreign))} is not an atom a unit "
                          f"evaluates; fix: build terms from {', '.join(UNIT_ATOMS)}, exp(-t_on/TAU), "
                          "sin(F) and cos(F) (docs/protocol.md, section 4)")
    key = next((k for k in ("coefficients", "coefficients_dps") if k in doc), None)
    if key is None:
        raise ConfigError(f"{path}: field 'coefficients' is missing; fix: add coefficients: {{x: [...], "
                          "y: [...], z: [...]}} with one value per term in deg/s per term unit")
    raw = doc[key]
    if isinstance(raw, dict):
        missing = [a for a in AXES if a not in raw]
        if missing:
            raise ConfigError(f"{path}: field '{key}' lacks axes {missing}; fix: give x, y and z")
        rows = [raw[a] for a in AXES]
    elif isinstance(raw, list) and len(raw) == 3:
        rows = raw
    else:
        raise ConfigError(f"{path}: field '{key}' must be {{x: [...], y: [...], z: [...]}} or a list of 3 "
                          "rows (x, y, z)")
    out: list[list[float]] = []
    for axis, row in zip(AXES, rows, strict=True):
        if not isinstance(row, list) or len(row) != len(terms):
            n = len(row) if isinstance(row, list) else type(row).__name__
            raise ConfigError(f"{path}: field '{key}.{axis}' has {n} values but there are {len(terms)} "
                              "terms; fix: give one coefficient per term, in the order of 'terms'")
        vals = []
        for i, v in enumerate(row):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"{path}: field '{key}.{axis}[{i}]' (term {terms[i]!r}) is {v!r}; fix: "
                                  "a finite number in deg/s per term unit")
            if abs(v) > MAX_PUSH_COEFF_DPS:
                raise ConfigError(f"{path}: field '{key}.{axis}[{i}]' (term {terms[i]!r}) is {v!r} deg/s "
                                  f"per term unit, beyond the {MAX_PUSH_COEFF_DPS:g} a unit takes; fix: "
                                  "coefficients are in deg/s (a deg/h figure is 3600 times larger)")
            vals.append(float(v))
        out.append(vals)
    return terms, out
