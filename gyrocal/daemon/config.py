"""The daemon's YAML configuration: loaded once, checked once, every error naming file, field, fix.

Why a table-driven checker instead of a schema library: the messages are the product here. A
navigation engineer editing /etc/gyrocal/gyrocal.yaml on a vehicle must read exactly which field is
wrong and what to write instead, in one line of the journal.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from gyrocal.errors import ConfigError, yaml_error_text
from gyrocal.model.bias_kalman import load_bias_spec
from gyrocal.model.convergence import ConvergenceConfig
from gyrocal.model.terms import SEED000_TERMS, read_terms_file
from gyrocal.protocol import termsets

DEFAULT_CONFIG = "default.yaml"

# section -> field -> (types, default, fix hint)
_SCHEMA: dict[str, dict[str, tuple[tuple[type, ...], Any, str]]] = {
    "link": {
        "kind": ((str,), "serial", "write `serial` or `can`"),
        "url": ((str,), "auto", "write a device such as /dev/gyrocal-imu, a pyserial URL, or `auto`"),
        "baudrate": ((int,), 921600, "write a baud rate such as 921600"),
        "can": ((dict,), {}, "write python-can Bus arguments, e.g. {interface: socketcan, channel: can0}; "
                "interface/channel left out come from python-can's config (CAN_INTERFACE, ~/.canrc)"),
        "mavlink": ((dict,), {}, "write MAVLink link options, e.g. {autopilot: px4} (docs/mavlink.md)"),
        "reconnect_max_s": ((int, float), 1.0,
                            "write the longest reconnect back-off in seconds (the engine caps it at 1 s)"),
        "can_node_id": ((int,), 0, "write the unit's CAN node id, an integer 0 to 15"),
    },
    "virtual_unit": {
        "enabled": ((bool,), False, "write true or false"),
        "seed": ((int,), 1, "write an integer seed"),
        "rate_hz": ((int, float), 1000, "write a sample rate in Hz, 1 to 2000"),
        "dwell_s": ((int, float), 1.2, "write the dwell per pose in seconds"),
        "move_s": ((int, float), 0.4, "write the rotation time between poses in seconds"),
        "schedule": ((str,), "", "write the path of a YAML schedule, or leave it out for the tumble"),
        "extra_args": ((list,), [], "write a list of extra `gyrocal sim` arguments"),
    },
    "estimator": {
        "method": ((str,), "rls", "write rls, nlms, lms or kf"),
        "terms": ((str, list), "seed000", "write `seed000`, a list of term names, or a YAML terms file"),
        "forgetting": ((int, float), 1.0, "write a forgetting factor in (0.9, 1]"),
        "step": ((int, float), 0.5, "write an NLMS/LMS step size in (0, 2)"),
        "convergence": ((dict,), {}, "write a mapping of convergence thresholds"),
    },
    "validation": {
        "holdout_every": ((int,), 5, "write an integer >= 2: every n-th still block is held out"),
        "block_s": ((int, float), 0.5, "write the still-block length in seconds"),
        "min_improvement": ((int, float), 0.2, "write a fraction in [0, 1)"),
        "min_holdout_blocks": ((int,), 6, "write the least number of held-out blocks before validating"),
    },
    "push": {
        "ack_timeout_s": ((int, float), 1.0, "write a timeout in seconds"),
        "retries": ((int,), 3, "write the number of attempts, >= 1"),
        "target_drift_dph": ((int, float), 0.2,
                             "write the predicted drift RMS [deg/h] below which a set is pushed"),
        "min_cut": ((int, float), 20.0,
                    "write the factor by which the predicted drift left must undercut the drift removed"),
        "bias_first": ((bool,), True, "write true or false: push a bias-only set first after a switch-on"),
        "wander_horizon_s": ((int, float), 600.0,
                             "write the seconds over which the bias wander's drift is weighed by the gate"),
    },
    "monitor": {
        "alarm_ratio": ((int, float), 3.0, "write a ratio > 1"),
        "window_s": ((int, float), 10.0, "write a window in seconds"),
        "alarm_floor_dps": ((int, float), 0.002, "write the smallest residual [deg/s] that can alarm"),
    },
    "store": {
        "keep_versions": ((int,), 1000, "write how many calibration versions to keep per unit, or 0 for all"),
    },
    "site": {
        "latitude_deg": ((int, float, type(None)), None,
                         "write the latitude where the unit is calibrated, in degrees, north positive "
                         "(-90 to 90), or leave it out"),
    },
    "still": {
        "window_s": ((int, float), 0.4, "write the still-detector window in seconds"),
        "k_std": ((int, float), 4.0, "write the multiple of the unit's quiet gyro/accel spread, > 1"),
        "k_turn": ((int, float), 8.0, "write the multiple of the turn the unit's noise gives, > 1"),
        "margin_s": ((int, float), 0.1, "write the seconds cut from each end of a still stretch"),
        "min_run_s": ((int, float), 0.5, "write the shortest still stretch kept, in seconds"),
        "learn_s": ((int, float), 1.0, "write the seconds after switch-on that teach the noise level"),
        "memory_s": ((int, float), 120.0, "write the seconds of history the noise level tracks"),
        # retired absolute thresholds: accepted and ignored (the engine logs what replaced them)
        "gyro_std_dps": ((int, float, type(None)), None, "delete it; still.k_std replaced it"),
        "accel_tol_g": ((int, float, type(None)), None, "delete it; still.k_std replaced it"),
    },
}


@dataclass(frozen=True)
class Range:
    """The allowed interval of a numeric field; ``lo_open``/``hi_open`` exclude the bound itself.

    Why every number has one: a value of the right type can still stop the daemon (block_s: 0 is a
    division by zero at the next session) or make it lie (ack_timeout_s: -1 times out every push), and
    the same check runs at start and at SIGHUP reload, so a bad edit is refused before it is used.
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    unit: str = ""

    def contains(self, v: float) -> bool:
        if not math.isfinite(v):
            return False
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return not (self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi))

    def text(self) -> str:
        left = "(" if self.lo_open or self.lo is None else "["
        right = ")" if self.hi_open or self.hi is None else "]"
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        return f"{left}{lo}, {hi}{right}" + (f" {self.unit}" if self.unit else "")


def _gt(lo: float, hi: float, unit: str = "") -> Range:
    """(lo, hi]: a strictly positive quantity with a sane ceiling."""
    return Range(lo, hi, lo_open=True, unit=unit)


# dotted field -> allowed range. EVERY int/float field of _SCHEMA must have a line here (a test checks);
# a new field adds its line next to its schema entry's section.
_RANGES: dict[str, Range] = {
    "link.baudrate": Range(300, 20_000_000, unit="baud"),
    "link.reconnect_max_s": _gt(0, 3600, "s"),
    "virtual_unit.seed": Range(0, 2**32 - 1),
    "virtual_unit.rate_hz": Range(1, 2000, unit="Hz"),
    "virtual_unit.dwell_s": _gt(0, 3600, "s"),
    "virtual_unit.move_s": _gt(0, 600, "s"),
    "estimator.forgetting": Range(0.9, 1.0, lo_open=True),
    "estimator.step": Range(0, 2, lo_open=True, hi_open=True),
    "validation.holdout_every": Range(2, 1000),
    "validation.block_s": Range(0.01, 60, unit="s"),
    "validation.min_improvement": Range(0, 1, hi_open=True),
    "validation.min_holdout_blocks": Range(1, 100_000),
    "push.ack_timeout_s": _gt(0, 60, "s"),
    "push.retries": Range(1, 100),
    "monitor.alarm_ratio": _gt(1, 1000),
    "monitor.window_s": _gt(0, 86_400, "s"),
    "monitor.alarm_floor_dps": Range(0, 10, unit="deg/s"),
    "still.window_s": _gt(0, 60, "s"),
    "still.k_std": _gt(1, 1000),
    "still.k_turn": _gt(1, 1000),
    "still.margin_s": Range(0, 60, unit="s"),
    "still.min_run_s": _gt(0, 3600, "s"),
    "still.learn_s": _gt(0, 3600, "s"),
    "still.memory_s": _gt(0, 86_400, "s"),
    "still.gyro_std_dps": _gt(0, 100, "deg/s"),  # retired (accepted, ignored): still.k_std replaced it
    "still.accel_tol_g": _gt(0, 1, "g"),  # retired (accepted, ignored)
    "link.can_node_id": Range(0, 15),
    "push.target_drift_dph": _gt(0, 1e6, "deg/h"),
    "push.min_cut": _gt(1, 1e6),
    "push.wander_horizon_s": _gt(0, 1e7, "s"),
    "store.keep_versions": Range(0, 10**9),
    "site.latitude_deg": Range(-90, 90, unit="deg"),
}

_TOP = {
    "state_dir": ((str,), "auto", "write a directory path, or `auto`"),
    "control_socket": ((str,), "auto", "write a socket path, or `auto`"),
    "watchdog": ((bool,), True, "write true or false"),
}


@dataclass
class DaemonConfig:
    """The checked configuration. Sections are plain dicts with every default filled in."""

    link: dict[str, Any]
    virtual_unit: dict[str, Any]
    estimator: dict[str, Any]
    validation: dict[str, Any]
    push: dict[str, Any]
    monitor: dict[str, Any]
    store: dict[str, Any]
    site: dict[str, Any]
    still: dict[str, Any]
    state_dir: Path
    control_socket: Path
    watchdog: bool = True
    source: str = "<default>"
    terms: list[str] = field(default_factory=lambda: list(SEED000_TERMS))


class _UniqueKeyLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses a key given twice in one mapping. PyYAML keeps the last one
    silently, so a second `store:` or `push:` section would undo the first without a word."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"field {key!r} appears twice; keep one", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def default_config_path() -> Path:
    return Path(str(resources.files("gyrocal") / "configs" / DEFAULT_CONFIG))


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> DaemonConfig:
    """Load and check a config file (the packaged default when ``path`` is None)."""
    p = Path(path) if path is not None else default_config_path()
    name = str(p)
    try:
        doc = yaml.load(p.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader)
    except FileNotFoundError:
        raise ConfigError(f"{name}: no such config file; pass an existing file to --config") from None
    except UnicodeDecodeError as err:
        # a Latin-1 degree sign in a comment crashed `gyrocal run` with a traceback, a restart loop
        # under systemd (an operator's audit)
        line = p.read_bytes()[: err.start].count(b"\n") + 1
        raise ConfigError(f"{name}: line {line}: byte 0x{err.object[err.start]:02x} is not UTF-8 (a degree "
                          "sign or accent saved as Latin-1?); save the file as UTF-8") from None
    except OSError as err:
        raise ConfigError(f"{name}: cannot read the config ({err.strerror})") from None
    except yaml.YAMLError as err:
        raise ConfigError(yaml_error_text(name, err)) from None
    if doc is None:
        if path is not None and not overrides:
            # an empty file (a botched edit) was refused as "field 'link.url' is 'auto'", which did not
            # say the file was empty (an operator's soak)
            raise ConfigError(f"{name}: the file is empty (or only comments); write at least a link: "
                              "section, e.g. from configs/gyrocal.example.yaml (docs/operations.md)")
        doc = {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{name}: the top level must be a mapping of sections (link:, estimator:, ...)")
    for key, value in (overrides or {}).items():
        section, _, fld = key.partition(".")
        if fld:
            doc.setdefault(section, {})[fld] = value
        else:
            doc[key] = value
    return _check(doc, name)


def _check_field(name: str, dotted: str, value: Any, spec: tuple[tuple[type, ...], Any, str]) -> Any:
    types, _, fix = spec
    if isinstance(value, bool) and bool not in types:
        raise ConfigError(f"{name}: field '{dotted}' is {value!r}; {fix}")
    if not isinstance(value, types):
        raise ConfigError(f"{name}: field '{dotted}' is {value!r}; {fix}")
    rng = _RANGES.get(dotted)
    if rng is not None and isinstance(value, int | float) and not rng.contains(value):
        raise ConfigError(f"{name}: field '{dotted}' is {value!r}, outside {rng.text()}; {fix}")
    return value


def _check(doc: dict[str, Any], name: str) -> DaemonConfig:
    unknown = set(doc) - set(_SCHEMA) - set(_TOP)
    if unknown:
        key = sorted(unknown)[0]
        raise ConfigError(
            f"{name}: unknown field '{key}'; known sections are {', '.join([*_SCHEMA, *_TOP])}"
        )
    sections: dict[str, dict[str, Any]] = {}
    for section, fields in _SCHEMA.items():
        given = doc.get(section) or {}
        if not isinstance(given, dict):
            raise ConfigError(f"{name}: field '{section}' must be a mapping of its fields")
        extra = set(given) - set(fields)
        if extra:
            key = sorted(extra)[0]
            raise ConfigError(
                f"{name}: unknown field '{section}.{key}'; {section} takes {', '.join(fields)}"
            )
        out = {}
        for fld, spec in fields.items():
            value = given.get(fld, spec[1])
            out[fld] = _check_field(name, f"{section}.{fld}", value, spec)
        sections[section] = out
    top = {k: _check_field(name, k, doc.get(k, spec[1]), spec) for k, spec in _TOP.items()}
    _check_ranges(sections, name)
    terms = _resolve_terms(sections["estimator"]["terms"], name)
    return DaemonConfig(
        **sections,
        state_dir=_state_dir(top["state_dir"]),
        control_socket=_socket_path(top["control_socket"]),
        watchdog=top["watchdog"],
        source=name,
        terms=terms,
    )


def _fail(name: str, dotted: str, value: Any, fix: str) -> None:
    raise ConfigError(f"{name}: field '{dotted}' is {value!r}; {fix}")


def _check_ranges(s: dict[str, dict[str, Any]], name: str) -> None:
    link, est, val = s["link"], s["estimator"], s["validation"]
    if link["kind"] not in ("serial", "can", "mavlink"):
        _fail(name, "link.kind", link["kind"], "write `serial` or `can` (or `mavlink` for an autopilot)")
    if link["kind"] == "can" and not s["virtual_unit"]["enabled"]:
        from gyrocal.drivers.can_defaults import with_python_can_defaults

        link["can"] = with_python_can_defaults(link["can"], f"{name}: field 'link.can'")
        if not link["can"].get("interface"):
            _fail(name, "link.can", link["can"], "give python-can Bus arguments, e.g. {interface: socketcan, "
                  "channel: can0}, or configure python-can (CAN_INTERFACE/CAN_CHANNEL, /etc/can.conf, "
                  "~/.canrc)")
    if link["url"] == "auto" and link["kind"] == "serial" and not s["virtual_unit"]["enabled"]:
        _fail(name, "link.url", "auto", "`auto` (the default, when link.url is left out) is the virtual "
              "unit's pty and needs virtual_unit.enabled: true; name the device, e.g. link: {url: "
              "/dev/gyrocal-imu}")
    if est["method"] not in ("rls", "nlms", "lms", "kf"):
        _fail(name, "estimator.method", est["method"], "write rls, nlms, lms or kf")
    if est["method"] == "kf":  # the bias intensities come from the terms file analyze wrote
        load_bias_spec(est["terms"], name)
    if not link["url"].strip():
        _fail(name, "link.url", link["url"], "name the device, e.g. /dev/gyrocal-imu, or write `auto`")
    extra = s["virtual_unit"]["extra_args"]
    if not all(isinstance(a, str) for a in extra):
        _fail(name, "virtual_unit.extra_args", extra, 'write a list of strings, e.g. ["--nak-next", "1"]')
    # ranges of single fields are checked in _check_field (_RANGES); here only what ties fields together
    if s["monitor"]["window_s"] < val["block_s"]:
        _fail(name, "monitor.window_s", s["monitor"]["window_s"],
              f"write a window >= validation.block_s ({val['block_s']:g} s): it holds whole still blocks")
    ConvergenceConfig.from_dict(est["convergence"], name, "estimator.convergence")  # raises with the field


def _resolve_terms(value: str | list[Any], name: str) -> list[str]:
    if value == "seed000":
        names = list(SEED000_TERMS)
    elif isinstance(value, list):
        names = [str(v) for v in value]
    else:
        path = Path(value)
        if not path.is_absolute():
            path = Path(name).parent / path
        try:
            names = read_terms_file(path)
        except ConfigError as err:
            raise ConfigError(f"{name}: field 'estimator.terms': {err}; write `seed000`, a list of terms, "
                              "or an existing terms file") from None
    try:  # the daemon evaluates the terms as the unit does, on what a sample carries; it registers the
        # set (protocol.md, section 4), and whether the unit knows it, the unit says
        termsets.register_unit_terms(names)
    except ConfigError as err:
        raise ConfigError(f"{name}: field 'estimator.terms': {err}") from None
    return names


def _writable_dir(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(path, os.W_OK)


def _state_dir(value: str) -> Path:
    if value != "auto":
        return Path(value).expanduser()
    if os.environ.get("STATE_DIRECTORY"):  # set by systemd's StateDirectory=
        return Path(os.environ["STATE_DIRECTORY"].split(":")[0])
    system = Path("/var/lib/gyrocal")
    if _writable_dir(system):
        return system
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "gyrocal"


def _socket_path(value: str) -> Path:
    if value != "auto":
        return Path(value).expanduser()
    if os.environ.get("GYROCAL_SOCKET"):
        return Path(os.environ["GYROCAL_SOCKET"])
    if os.environ.get("RUNTIME_DIRECTORY"):  # set by systemd's RuntimeDirectory=
        return Path(os.environ["RUNTIME_DIRECTORY"].split(":")[0]) / "control.sock"
    system = Path("/run/gyrocal")
    if _writable_dir(system):
        return system / "control.sock"
    from gyrocal.daemon.control import user_runtime_dir  # one definition for daemon and client

    return user_runtime_dir() / "control.sock"  # created 0700 and owner-checked by ControlServer.start
