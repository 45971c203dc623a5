"""Which samples the analysis may use: still segments, or every sample when reference rates exist.

Why a still detector: the baseline model (gravity-dependent drift plus white noise) predicts the gyro
output only where the true rate is known. Without reference rates that is where the unit rests
(true rate ~ 0, apart from earth rate). With ``ref_w*`` columns the true rate is known everywhere, so
every sample is usable and the scale factor becomes testable.

The detector itself (gyro first, accelerometer second, thresholds relative to the log's own quiet
level) lives in gyrocal/model/still.py, shared with `gyrocal fit`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from gyrocal.model.still import detect_still, sample_rate_hz

AXES = ("x", "y", "z")


@dataclass
class Usable:
    """The samples the analysis fits and tests on, and how they group.

    Arrays are indexed by used sample (length M). ``run`` numbers contiguous stretches (no gap,
    one session); a moving average never crosses a run boundary.
    """

    index: np.ndarray  # (M,) indices into the log's rows
    run: np.ndarray  # (M,) run id, contiguous and non-decreasing
    session: np.ndarray  # (M,) session number
    rate_hz: float  # nominal sample rate [Hz]
    with_reference: bool  # True when ref_w* columns were subtracted and moving samples kept

    @property
    def n_runs(self) -> int:
        return int(self.run[-1]) + 1 if self.run.size else 0


def usable_samples(columns: Mapping[str, np.ndarray], still: np.ndarray | None = None) -> Usable:
    """Choose the samples to analyse and group them into runs (contiguous, one session each)."""
    t = np.asarray(columns["t"], dtype=float)
    session = np.asarray(columns["session"], dtype=float)
    rate = sample_rate_hz(t, session)
    with_ref = all(f"ref_w{a}" in columns for a in AXES)
    if with_ref:
        mask = np.ones(t.size, dtype=bool)
    else:
        mask = detect_still(columns, rate) if still is None else still.astype(bool)
    index = np.flatnonzero(mask)
    if index.size == 0:
        return Usable(index, index.copy(), index.astype(float), rate, with_ref)
    gap = np.diff(t[index]) > max(5.0 / rate, 1.0)  # bursty loggers pause ~0.1-0.5 s
    new = np.concatenate(([True], (np.diff(index) > 1) | gap | (np.diff(session[index]) != 0)))
    run = np.cumsum(new) - 1
    return Usable(index, run, session[index], rate, with_ref)
