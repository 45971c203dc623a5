"""Functional-link terms built from a model spec: a list of term names.

Seed 000 (eq. 10) expands the gravity vector (gx, gy, gz) [g] into ten terms. We generalise the
expansion so that a model can grow without code changes (seed 004's temperature inputs, a warm-up
transient, a sinusoid, a scale factor): a term is a product of factors, each factor an atom raised
to an integer power.

Atoms:
- any log column or derived column: ``gx gy gz`` [g] (the specific force, i.e. ax ay az),
  ``temp`` [degC], ``dtemp`` [degC/s], ``t_on`` [s since switch-on], ``t`` [s], ``ref_wx`` [deg/s], ...
- ``exp(-t_on/TAU)``: a warm-up transient with time constant TAU [s];
- ``sin(F)`` and ``cos(F)``: sin(2*pi*F*t) with F in Hz and t in s.

Examples: ``1``, ``gx``, ``gx^2``, ``gx*gy``, ``temp*dtemp``, ``exp(-t_on/300)``, ``sin(1.7)``.
A coefficient is in deg/s per unit of its term (deg/s per g, deg/s per degC, ...).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from gyrocal.errors import ConfigError

SEED000_TERMS: tuple[str, ...] = (
    "1", "gx", "gy", "gz", "gx^2", "gy^2", "gz^2", "gx*gy", "gy*gz", "gx*gz",
)
"""Seed 000 eq. (10), in the paper's order d0..d9."""

_ALIASES = {"gx": "ax", "gy": "ay", "gz": "az"}
_EXP = re.compile(r"^exp\(-t_on/([0-9.eE+-]+)\)$")
_TRIG = re.compile(r"^(sin|cos)\(([0-9.eE+-]+)\)$")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class Factor:
    """One atom raised to a positive integer power."""

    atom: str
    power: int = 1

    def evaluate(self, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        return _atom(self.atom, columns) ** self.power


@dataclass(frozen=True)
class Term:
    """A product of factors; the empty product is the constant term ``1``."""

    name: str
    factors: tuple[Factor, ...]

    @property
    def atoms(self) -> set[str]:
        return {f.atom for f in self.factors}

    def evaluate(self, columns: Mapping[str, np.ndarray], n: int) -> np.ndarray:
        out = np.ones(n)
        for f in self.factors:
            out = out * f.evaluate(columns)
        return out


def parse_term(name: str) -> Term:
    """Parse one term name; raise ConfigError with the fix when it is malformed."""
    text = name.replace(" ", "")
    if text == "1":
        return Term("1", ())
    factors = []
    for part in _split_product(text):
        atom, power = part, 1
        if "^" in part and not part.endswith(")"):
            atom, _, p = part.rpartition("^")
            if not p.isdigit() or int(p) < 1:
                raise ConfigError(f"term {name!r}: power {p!r} must be a positive integer, e.g. temp^2")
            power = int(p)
        if not (_NAME.match(atom) or _EXP.match(atom) or _TRIG.match(atom)):
            raise ConfigError(
                f"term {name!r}: factor {atom!r} is not a column name, exp(-t_on/TAU) or "
                "sin(F)/cos(F); write e.g. 'gx*gy', 'temp^2', 'exp(-t_on/300)' or 'sin(1.7)'"
            )
        factors.append(Factor(atom, power))
    return Term(text, tuple(factors))


def _split_product(text: str) -> list[str]:
    parts, depth, cur = [], 0, ""
    for ch in text:
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
        if ch == "*" and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    parts.append(cur)
    if any(not p for p in parts):
        raise ConfigError(f"term {text!r}: empty factor; write factors joined by '*', e.g. gx*gy")
    return parts


def _atom(atom: str, columns: Mapping[str, np.ndarray]) -> np.ndarray:
    if atom in columns:
        return np.asarray(columns[atom], dtype=np.float64)
    if atom in _ALIASES and _ALIASES[atom] in columns:
        return np.asarray(columns[_ALIASES[atom]], dtype=np.float64)
    m = _EXP.match(atom)
    if m:
        return np.exp(-_atom("t_on", columns) / float(m.group(1)))
    m = _TRIG.match(atom)
    if m:
        fn = np.sin if m.group(1) == "sin" else np.cos
        return fn(2.0 * np.pi * float(m.group(2)) * _atom("t", columns))
    raise ConfigError(
        f"term atom {atom!r} needs a column {atom!r} that the data does not have; "
        f"available: {', '.join(sorted(columns))}"
    )


@dataclass(frozen=True)
class TermSpec:
    """An ordered list of functional-link terms (seed 000 eq. 10 by default)."""

    terms: tuple[Term, ...]

    @classmethod
    def parse(cls, names: Sequence[str] = SEED000_TERMS) -> TermSpec:
        terms = tuple(parse_term(n) for n in names)
        seen = [t.name for t in terms]
        if len(set(seen)) != len(seen):
            raise ConfigError(f"term list {list(names)} names a term twice; list each term once")
        return cls(terms)

    @property
    def names(self) -> list[str]:
        return [t.name for t in self.terms]

    @property
    def atoms(self) -> set[str]:
        return set().union(*(t.atoms for t in self.terms)) if self.terms else set()

    def __len__(self) -> int:
        return len(self.terms)

    def design(self, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        """The design matrix, shape (N, P), each column a term in its physical unit."""
        n = len(next(iter(columns.values())))
        return np.column_stack([t.evaluate(columns, n) for t in self.terms])

    def row(self, columns: Mapping[str, float]) -> np.ndarray:
        """One sample's term vector, shape (P,), from scalar column values."""
        arrays = {k: np.asarray([v], dtype=np.float64) for k, v in columns.items()}
        return self.design(arrays)[0]


T_ORIGIN_KEY = "t_origin"
"""Log metadata key: ``switch_on`` when ``t`` is the unit's time since switch-on (docs/logformat.md)."""


def read_terms_file(path: str | Path) -> list[str]:
    """The term names of a terms file: YAML ``terms: [...]`` as `gyrocal analyze` writes it, or a bare
    list. Read by `gyrocal fit --terms-file`, the daemon's ``estimator.terms`` and `gyrocal sim
    --terms`; raises ConfigError naming the file and the fix."""
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{path}: cannot read the terms file ({err})") from None
    names = doc.get("terms") if isinstance(doc, dict) else doc
    if not isinstance(names, list) or not names or not all(isinstance(n, str | int) for n in names):
        raise ConfigError(f"{path}: field 'terms' must be a list of term names, e.g. terms: ['1', gx, temp]")
    return [str(n) for n in names]


def from_switch_on(metadata: Mapping[str, str]) -> bool:
    """Whether a log's ``t`` is the unit's time since switch-on (its metadata says so)."""
    return metadata.get(T_ORIGIN_KEY, "") == "switch_on"


def derived_columns(
    columns: Mapping[str, np.ndarray], rate_window_s: float = 20.0, t_from_switch_on: bool = False
) -> dict[str, np.ndarray]:
    """Add the derived atoms a model may use: ``t_on`` [s] and ``dtemp`` [degC/s].

    ``t_on`` is the time since the first sample of each session (switch-on), or ``t`` itself when
    ``t_from_switch_on`` says the log's time is the unit's time since switch-on (a link recording,
    metadata ``t_origin: switch_on``), which a capture started late would otherwise shift. ``dtemp``
    is the temperature rate from a least-squares slope over a centred window of ``rate_window_s``,
    computed per session so that a switch-on never produces a spurious step in the rate.
    """
    out = dict(columns)
    t = np.asarray(columns["t"], dtype=np.float64)
    session = np.asarray(columns.get("session", np.zeros_like(t)))
    t_on = np.empty_like(t)
    dtemp = np.zeros_like(t)
    has_temp = "temp" in columns
    for s in np.unique(session):
        idx = np.flatnonzero(session == s)
        ts = t[idx]
        t_on[idx] = ts if t_from_switch_on else ts - ts[0]
        if has_temp and idx.size > 2:
            dtemp[idx] = _windowed_slope(ts, np.asarray(columns["temp"])[idx], rate_window_s)
    out["t_on"] = t_on
    if has_temp:
        out["dtemp"] = dtemp
    return out


def _windowed_slope(t: np.ndarray, y: np.ndarray, window_s: float) -> np.ndarray:
    """Least-squares slope of y over t within +-window_s/2 of each sample, via cumulative sums."""
    t0 = t - t[0]
    c = np.concatenate(([0.0], np.cumsum(np.ones_like(t0))))
    ct = np.concatenate(([0.0], np.cumsum(t0)))
    cy = np.concatenate(([0.0], np.cumsum(y)))
    ctt = np.concatenate(([0.0], np.cumsum(t0 * t0)))
    cty = np.concatenate(([0.0], np.cumsum(t0 * y)))
    lo = np.searchsorted(t0, t0 - window_s / 2, side="left")
    hi = np.searchsorted(t0, t0 + window_s / 2, side="right")
    n = c[hi] - c[lo]
    st, sy = ct[hi] - ct[lo], cy[hi] - cy[lo]
    stt, sty = ctt[hi] - ctt[lo], cty[hi] - cty[lo]
    den = n * stt - st * st
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = np.where(den > 1e-12, (n * sty - st * sy) / np.where(den > 1e-12, den, 1.0), 0.0)
    return slope
