"""Bursty logger time stamps: detect them and re-time the samples to the sensor's sample clock.

Why: a logger that reads a sensor's FIFO in bursts writes its own read time into ``t``: intervals
of 1-2 ms within a burst, then 40-70 ms between bursts (sunsided's MPU6050 logger). The sensor
sampled regularly all along, so such a ``t`` scrambles every frequency above about 2 Hz: a real
31 Hz line is smeared and the burst rhythm itself shows up as spectral peaks (5.14 Hz on sunsided).

A session is bursty when many intervals are far from the rate (``FAR_SHARE`` of them under half
or over twice the median spacing implied by the sample count) while the sample count says the
samples were regular: the time stamps stay within ``MAX_LAG_S`` (or ``MAX_LAG_FRACTION`` of the
span) of a straight line through sample index, so no samples were lost. Such a session is re-timed
to that line (least squares of t on the sample index: the sample clock's rate and phase).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

FAR_SHARE = 0.2
MAX_LAG_S = 0.5
MAX_LAG_FRACTION = 0.002


def bursty(t: np.ndarray) -> tuple[bool, dict]:
    """Is this one session's time column (N,) [s] bursty while the samples were regular?"""
    n = t.size
    if n < 20:
        return False, {}
    i = np.arange(n, dtype=float)
    slope, icpt = np.polyfit(i, t, 1)
    if slope <= 0:
        return False, {}
    d = np.diff(t)
    far = float(np.mean((d < 0.5 * slope) | (d > 2.0 * slope)))
    lag = float(np.max(np.abs(t - (icpt + slope * i))))
    span = float(t[-1] - t[0])
    info = {"rate_hz": round(1.0 / slope, 4), "far_interval_share": round(far, 3),
            "max_lag_s": round(lag, 4), "interval_cv": round(float(np.std(d) / np.mean(d)), 3)}
    regular = lag <= max(MAX_LAG_S, MAX_LAG_FRACTION * span)
    return bool(far >= FAR_SHARE and regular), info


def retime(columns: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], list[dict]]:
    """A copy of the columns with bursty sessions re-timed to their sample clock, and what was done.

    Each entry of the returned list names a re-timed session, its sample-clock rate [Hz], the share
    of intervals far from it and the largest lag of the logger's stamps behind the clock [s].
    """
    out = {k: np.asarray(v) for k, v in columns.items()}
    t = np.asarray(columns["t"], float).copy()
    session = np.asarray(columns.get("session", np.zeros_like(t)), float)
    notes = []
    for s in np.unique(session):
        m = np.flatnonzero(session == s)
        is_bursty, info = bursty(t[m])
        if not is_bursty:
            continue
        i = np.arange(m.size, dtype=float)
        slope, icpt = np.polyfit(i, t[m], 1)
        t[m] = icpt + slope * i
        notes.append({"session": int(s), **info})
    out["t"] = t
    return out, notes


def describe(notes: list[dict]) -> str:
    """One sentence for the findings' evidence."""
    if not notes:
        return ""
    rates = ", ".join(f"{n['rate_hz']:g}" for n in notes)
    share = max(n["far_interval_share"] for n in notes)
    lag = max(n["max_lag_s"] for n in notes)
    return (f"The logger's time stamps were bursty ({len(notes)} session(s): up to {share:.0%} of the "
            f"intervals far from the rate, while the stamps stay within {lag:.2g} s of a regular clock); "
            f"the samples were re-timed to the sample clock ({rates} Hz) before the analysis.")
