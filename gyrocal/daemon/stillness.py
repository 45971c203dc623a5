"""On-line still detection: the daemon's side of the one still rule (gyrocal/model/still.py).

Seed 000's model is a static one: gravity terms explain drift only while the unit rests. During a
rotation the gyro reads the true rate and the accelerometer sees centripetal terms, so those samples
must not reach the estimator. The rule, its thresholds and its statistics are model/still.py's, the
same that `gyrocal fit` and `gyrocal analyze` apply to a log; this module only maps the daemon's
``still`` config section onto it and reports, for status, why samples are (not) still.

Thresholds are relative: the detector learns the unit's quiet level in the first ``learn_s`` seconds
after switch-on and keeps tracking it, so a 0.002 deg/s fibre gyro and a 0.5 deg/s MEMS part are
handled alike. Windows are in seconds, so the rule does not change with the sample rate.

Units: gyro deg/s, accel g, time s, rate Hz.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gyrocal.model.still import StillRule, StreamingStill

RULE_FIELDS = ("window_s", "k_std", "k_turn", "margin_s", "min_run_s", "learn_s", "memory_s")
"""The ``still`` config fields that map onto ``StillRule``."""

RETIRED_FIELDS = {
    "gyro_std_dps": "still.k_std (a multiple of the unit's own quiet level, learnt at switch-on)",
    "accel_tol_g": "still.k_std (the accelerometer's spread, relative to its own quiet level)",
}
"""Absolute thresholds of the old detector, and what replaced them."""


def rule_from_config(still_cfg: dict[str, Any] | None) -> StillRule:
    """The still rule from the daemon config's ``still`` section (missing fields: the defaults)."""
    cfg = still_cfg or {}
    return StillRule(**{k: float(cfg[k]) for k in RULE_FIELDS if cfg.get(k) is not None})


class StillDetector:
    """Feed blocks of samples (SAMPLE_DTYPE); get back the samples now decided, with their still flags."""

    def __init__(self, rate_hz: float, rule: StillRule | None = None) -> None:
        self.core = StreamingStill(rate_hz, rule)

    @classmethod
    def for_rate(cls, rate_hz: float, still_cfg: dict[str, Any] | None = None) -> StillDetector:
        return cls(rate_hz, rule_from_config(still_cfg))

    @property
    def rule(self) -> StillRule:
        return self.core.rule

    @property
    def lookahead_s(self) -> float:
        """Decisions come out this much later than the sample [s] (more while a stretch is young)."""
        return (self.core.ahead + self.core.margin) / self.core.rate_hz

    def reset(self) -> None:
        self.core.reset()

    def feed(self, block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.core.feed(block)

    def status(self) -> dict[str, Any]:
        """Why samples are or are not still: fraction, the learnt noise level, the thresholds in force."""
        c = self.core
        out: dict[str, Any] = {
            "rate_hz": c.rate_hz, "window_s": c.rule.window_s, "k_std": c.rule.k_std,
            "samples_decided": c.decided, "still_fraction": round(c.still_fraction, 4),
        }
        if c.levels is None:
            out["noise"] = None
            out["why"] = (f"learning the unit's noise level ({c.seen} of "
                          f"{int(c.rule.learn_s * c.rate_hz)} samples)")
            return out
        out["noise"] = c.levels.as_dict(c.rule)
        worst = float(np.max(c.levels.gyro_dps))
        if worst > c.rule.max_quiet_dps:
            out["why"] = (f"never at rest yet: the quietest gyro spread is {worst:.3g} deg/s, above "
                          f"{c.rule.max_quiet_dps:g} deg/s")
        elif c.decided and c.still_fraction == 0:
            out["why"] = "no still stretch yet: hold the unit at rest for at least " \
                         f"{c.rule.min_run_s + 2 * c.rule.margin_s + c.rule.window_s:.1f} s"
        else:
            out["why"] = ""
        return out
