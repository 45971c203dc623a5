"""When is an estimate good enough to push? The convergence rule and its thresholds.

An estimator is ``converged`` when all of these hold (docs/estimators.md):

1. it has used at least ``min_samples`` samples and the rank is at least ``min_rank``;
2. the windowed a-priori error is at the noise floor: its RMS over the last ``window`` samples is
   at most ``max_error_ratio`` times the least-squares residual RMS (per axis);
3. the determined coefficients have stopped moving: over the last ``window`` samples none moved by
   more than ``max_change_dps`` [deg/s];
4. the determined coefficients are known well enough: every finite 1-sigma is at most
   ``max_sigma_dps`` [deg/s].

The first rule that fails is the reason given; undetermined coefficients are excluded from 3 and 4
(they are never pushed as learned).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from gyrocal.errors import ConfigError


@dataclass(frozen=True)
class ConvergenceConfig:
    """Thresholds of the convergence rule; the daemon passes the YAML section ``convergence``."""

    window: int = 2000
    """Samples in the error / change window."""
    min_samples: int = 2000
    """Accepted samples before convergence can be declared."""
    min_rank: int = 1
    """Smallest acceptable rank of the information matrix (9 for seed 000's terms on a tumble)."""
    max_error_ratio: float = 1.5
    """Windowed a-priori error RMS / least-squares residual RMS, per axis."""
    max_change_dps: float = 2e-4
    """Largest change of a determined coefficient over one window [deg/s] (0.72 deg/h)."""
    max_sigma_dps: float = 1e-3
    """Largest 1-sigma of a determined coefficient [deg/s] (3.6 deg/h)."""

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, source: str = "config",
                  section: str = "convergence") -> ConvergenceConfig:
        """Build from a mapping; raise ConfigError naming the source, the field and the fix.

        ``section``: the dotted name the fields sit under in the source (the daemon's config says
        ``estimator.convergence``), so the message names the field as the file spells it."""
        if d is None:
            return cls()
        if not isinstance(d, Mapping):
            raise ConfigError(f"{source}: field '{section}' must be a mapping of field: value")
        known = {f.name: f for f in fields(cls)}
        out: dict[str, Any] = {}
        for key, value in d.items():
            if key not in known:
                raise ConfigError(
                    f"{source}: field '{section}.{key}' is unknown; use one of {', '.join(known)}")
            want_int = known[key].type in ("int", int)
            ok = isinstance(value, int) if want_int else isinstance(value, int | float)
            if isinstance(value, bool) or not ok:
                kind = "an integer" if want_int else "a number"
                raise ConfigError(f"{source}: field '{section}.{key}' is {value!r}, not {kind}; write e.g. "
                                  f"{key}: {getattr(cls(), key)}")
            strict = key in ("window", "max_error_ratio")
            if value < 0 or (strict and value <= 0):
                raise ConfigError(f"{source}: field '{section}.{key}' is {value!r}; write a number "
                                  f"{'> 0' if strict else '>= 0'}, e.g. {key}: {getattr(cls(), key)}")
            out[key] = int(value) if want_int else float(value)
        return cls(**out)


@dataclass(frozen=True)
class ConvergenceStatus:
    """The verdict, its reason in one sentence, and the figures behind it."""

    converged: bool
    reason: str
    metrics: dict[str, float]
