"""Still detection: which samples were taken with the unit at rest. One rule, off line and on line.

`gyrocal fit` (model/prep.py) and `gyrocal analyze` (analysis/segments.py) call ``detect_still`` on a
whole log; the daemon feeds ``StreamingStill`` block by block (daemon/stillness.py). Both apply the
same ``StillRule`` to the same rolling statistics, so a log's still periods are the same whichever
reads it. The only difference is where the unit's quiet level comes from:

- off line, the quantile over the whole log;
- on line, the same quantile over a bounded, decimated history of the stream (learnt in the first
  ``learn_s`` seconds after switch-on, then tracked; memory ``memory_s``).

The rule looks at the gyro first (the accelerometer alone lets slow hand motion in, as the mikoff
data shows) and at the accelerometer second (a constant-rate turn has a small gyro variance but a
turning gravity vector). Thresholds are relative to the unit's own quiet level, so the same rule
works for a 0.002 deg/s fibre gyro and a 0.5 deg/s MEMS part, and windows are in seconds, so it
works at 100 Hz and at 2 kHz. Units: gyro deg/s, accel g, time s, rate Hz.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

AXES = ("x", "y", "z")
_FIELDS = ("wx", "wy", "wz", "ax", "ay", "az")
QUIET_QUANTILE = 0.1
"""The quiet level is this quantile of the rolling std: still for at least this share of the log."""


@dataclass(frozen=True)
class StillRule:
    """The thresholds of the one still rule (all relative to the unit's quiet level, or in seconds).

    A sample is still when, in a window of ``window_s`` around it, every gyro axis has a rolling std
    below ``k_std`` times its quiet level, the rolling gyro mean stays within
    max(``band_k`` x quiet, ``band_floor_dps``) of the still median (a constant-rate turn is not
    still), and every accelerometer axis has a rolling std below ``k_std`` times its quiet level
    and no axis turns within the window (``k_turn``: gravity on the accelerometer, the rate on the
    gyro), and no gyro axis is flat through the whole window (``flat_axes``: one value, or a noise
    below FLAT_DPS: a stuck or railed sensor; a live gyro's noise spans many 1e-6 deg/s counts).
    Still stretches then lose ``margin_s`` at each end and are dropped when shorter than
    ``min_run_s``. A unit whose quiet level exceeds ``max_quiet_dps`` is never still: no gyro is
    that noisy at rest, so it has not been at rest yet; nor is a sample whose rolling gyro mean
    exceeds ``max_rate_dps`` along gravity (the rolling accelerometer mean; on every axis when there
    is none).

    A rest therefore yields still samples only when it lasts at least window + 2 margins + min_run
    (1.1 s with the defaults). The margins and minimum length are what hand-held real data needs
    (mikoff: shorter ones let settling motion in, and ``gyrocal analyze`` then mistakes a warm-up for
    a random walk); a unit whose schedule rests for less sets ``still.margin_s`` / ``min_run_s`` lower.
    """

    window_s: float = 0.4
    k_std: float = 4.0
    margin_s: float = 0.1
    min_run_s: float = 0.5
    quantile: float = QUIET_QUANTILE
    band_k: float = 8.0
    band_floor_dps: float = 0.5
    max_quiet_dps: float = 5.0
    max_rate_dps: float = 10.0
    """A rolling gyro mean beyond this [deg/s] along gravity is a turn, whatever the learnt centre: a
    unit that switches on turning about the vertical would otherwise learn the turn as its bias (MEMS
    biases are a few deg/s), and nothing else shows such a turn. Across gravity a turn turns gravity,
    which ``k_turn`` sees; there the cap refused an MPU-6050 log at rest whose x zero-rate offset was
    17 deg/s (within its +-20: "only 0 still samples", an outside check)."""
    k_turn: float = 8.0
    """Turning within a window: an axis whose second-half mean differs from its first-half mean by more
    than this many times what noise alone gives at rest, on the accelerometer [g] (gravity turning)
    or on the gyro [deg/s] (the rate changing: an angular acceleration). What noise gives is found
    from the noise's first and second differences (``turn_noise``), which a steady turn does not
    touch. A vehicle pitching or rolling at 0.2-0.4 deg/s is inside the gyro band's floor (0.5
    deg/s) and below 4 sigma of accelerometer spread, yet the turn is the drift learnt: false drift
    alarms of 100-740 deg/h where the unit left 0.3-13, and refinements refused (a fleet engineer's
    road drives). Rocking from switch-on made the quiet level itself: a turn level learnt from the
    samples' spread or the history's own turns let it all in, and a bias stage made an axis 3.4x
    worse (an integrator's check). At 400 Hz with 0.2 mg and 0.002 deg/s of noise, turns from about
    0.07 deg/s and angular accelerations from about 0.015 deg/s^2 are seen; a swing slower than both
    is not. 8, not 5: at 5 the hand-held and coloured MPU logs in data/ lost up to 17 % of their
    still samples to noise."""
    learn_s: float = 1.0
    """On line: seconds of data before the first decision (the quiet level is learnt on them)."""
    memory_s: float = 120.0
    """On line: the quiet level is the quantile over this much recent history."""

    def window(self, rate_hz: float) -> int:
        return max(3, int(round(self.window_s * rate_hz)))

    def margin(self, rate_hz: float) -> int:
        return int(round(self.margin_s * rate_hz))

    def min_run(self, rate_hz: float) -> int:
        return int(round(self.min_run_s * rate_hz))


RHO_MAX = 0.9
"""The largest lag-1 correlation of a noise that ``turn_noise`` believes (a colour factor of 4.4)."""

# the columns of a rolling-statistics row (``rolling_stats``), per axis x, y, z
GYRO_MEAN, GYRO_STD, ACCEL_STD = slice(0, 3), slice(3, 6), slice(6, 9)
GYRO_TURN, ACCEL_TURN = slice(9, 12), slice(12, 15)
GYRO_D1, ACCEL_D1, GYRO_D2, ACCEL_D2 = slice(15, 18), slice(18, 21), slice(21, 24), slice(24, 27)
ACCEL_MEAN = slice(27, 30)
GYRO_CHANGES = slice(30, 33)
STATS_COLUMNS = 33
FLAT_MIN_WINDOW = 20
"""Windows of fewer samples than this are never judged flat (``flat_axes``): at 10-50 Hz a
coarsely quantised quiet gyro may repeat one count for a whole short window."""
FLAT_DPS = 1e-5
"""A gyro axis whose sample-to-sample noise is below this [deg/s] in a window is judged flat
(``flat_axes``), as is one whose value does not change at all. A stuck sensor behind a unit's own
compensation is not one value: the unit subtracts its set's terms, whose accelerometer noise moves
the output by about 1e-6 deg/s (a stuck x at 2.0 deg/s behind v7 had a drift alarm and four bias
stages pushed: rc36a, live). The quietest live gyros are above 5e-5 deg/s per sample from 50 Hz up
(a 0.0005 deg/sqrt(h) fibre gyro)."""


def turn_noise(d1_std: np.ndarray, d2_std: np.ndarray, w: int) -> np.ndarray:
    """The standard deviation of a window's turn (second-half mean minus first-half mean, ``w``
    samples) that noise alone gives, from the spreads of the noise's first and second differences.

    Differences are blind to a steady turn: a unit rocking from switch-on inflates its samples' own
    spread, and a turn level learnt from it let the rocking in (an integrator's check). For a
    first-order (AR(1)) noise of variance s^2 and lag-1 correlation rho, var(d1) = 2 s^2 (1 - rho)
    and var(d2) = 2 s^2 (1 - rho)(3 - rho): rho = 3 - var(d2) / var(d1) (0 for white noise), and a
    half-window mean's variance is s^2 (1 + rho) / (1 - rho) / (w / 2). A sensor's low-pass filter
    (MPU DLPF) colours its noise that way. An axis whose differences are 0 (quantised, still): 0.
    """
    d1, d2 = np.asarray(d1_std, dtype=float), np.asarray(d2_std, dtype=float)
    ok = d1 > 0
    rho = np.clip(3.0 - (d2 / np.where(ok, d1, 1.0)) ** 2, 0.0, RHO_MAX)
    var = d1**2 / (2.0 * (1.0 - rho))
    return np.where(ok, 2.0 * np.sqrt(var * (1.0 + rho) / (1.0 - rho) / max(w, 1)), 0.0)


@dataclass
class QuietLevels:
    """The unit's quiet level: per-axis gyro std [deg/s], accel std [g], still gyro mean [deg/s], and
    the standard deviation at rest of a window's turn (``StillRule.k_turn``), accel [g] and gyro
    [deg/s]."""

    gyro_dps: np.ndarray
    accel_g: np.ndarray
    centre_dps: np.ndarray
    turn_g: np.ndarray
    turn_dps: np.ndarray

    def as_dict(self, rule: StillRule) -> dict[str, object]:
        """For status: the noise level and the thresholds in force."""
        band = np.maximum(rule.band_k * self.gyro_dps, rule.band_floor_dps)
        return {
            "gyro_noise_dps": dict(zip(AXES, self.gyro_dps.tolist(), strict=True)),
            "accel_noise_g": dict(zip(AXES, self.accel_g.tolist(), strict=True)),
            "gyro_std_limit_dps": dict(zip(AXES, (rule.k_std * self.gyro_dps).tolist(), strict=True)),
            "accel_std_limit_g": dict(zip(AXES, (rule.k_std * self.accel_g).tolist(), strict=True)),
            "gyro_mean_band_dps": dict(zip(AXES, band.tolist(), strict=True)),
            "gyro_centre_dps": dict(zip(AXES, self.centre_dps.tolist(), strict=True)),
            "accel_turn_limit_g": dict(zip(AXES, (rule.k_turn * self.turn_g).tolist(), strict=True)),
            "gyro_turn_limit_dps": dict(zip(AXES, (rule.k_turn * self.turn_dps).tolist(), strict=True)),
        }


GAP_S = 1.0
"""[s] An interval longer than this (and than GAP_FACTOR mean intervals) is a pause in the logging."""
GAP_FACTOR = 20.0


DROP_TOL = 0.1
"""An interval within this fraction of a whole number of sample periods is that many periods."""


def _intervals(t: np.ndarray, session: np.ndarray) -> np.ndarray:
    """Sample intervals [s] within sessions, pauses in the logging left out (``sample_rate_hz``)."""
    same = session[1:] == session[:-1]
    kept = np.diff(t)[same]
    if float(np.sum(kept)) <= 0:
        return kept
    for _ in range(2):
        keep = kept[kept <= max(GAP_S, GAP_FACTOR * float(np.mean(kept)))]
        if keep.size == 0 or float(np.sum(keep)) <= 0:
            break
        kept = keep
    return kept


def missing_samples(t: np.ndarray, session: np.ndarray) -> int:
    """Samples missing from a regular clock [count]: intervals of 2, 3, ... sample periods where most
    intervals are one period (each within DROP_TOL) and fewer samples are missing than there. 0 for a
    clock that is not regular (a bursty logger's read times, a jittered one)."""
    periods = _periods(_intervals(t, session))
    return 0 if periods is None else int(np.sum(periods) - periods.size)


def _periods(dt: np.ndarray) -> np.ndarray | None:
    """Each interval in sample periods (whole numbers), or None when the clock is not regular."""
    if dt.size < 10:
        return None
    med = float(np.median(dt))
    if med <= 0:
        return None
    ratio = dt / med
    k = np.round(ratio)
    if np.mean(np.abs(ratio - 1.0) <= DROP_TOL) < 0.5 or np.any(k < 1) \
            or np.any(np.abs(ratio - k) > DROP_TOL * k) or np.sum(k) > 2 * k.size:
        return None  # more missing than there: a logger's bursts (5 reads every 50 ms), not drops
    return k


def sample_rate_hz(t: np.ndarray, session: np.ndarray) -> float:
    """The sample rate [Hz] within sessions: samples per second of recording.

    The mean, not the median interval, because some loggers deliver samples in bursts (sunsided's
    time stamps alternate short and long intervals), where the median would overstate the rate.
    A pause in the logging is not part of the rate: intervals over ``GAP_S`` and ``GAP_FACTOR``
    times the mean are left out, twice (a one-hour pause in a 100 Hz log gave 2.7 Hz, and a 5 s one
    95 Hz: an outside check). A regular clock with samples missing (intervals of whole numbers of
    periods) counts the missing ones: 10 % of a 100 Hz log's rows dropped at random read 89.9 Hz, and
    the ARW 5 % high (an outside check); ``missing_samples`` says how many.
    """
    kept = _intervals(t, session)
    if float(np.sum(kept)) <= 0:
        return 1.0
    periods = _periods(kept)
    count = kept.size if periods is None else float(np.sum(periods))
    return float(count / float(np.sum(kept)))


def _window_bounds(n: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) of each of n rows' centred window of w samples, cut at the edges."""
    i = np.arange(n)
    return np.clip(i - w // 2, 0, n), np.clip(i + w - w // 2, 0, n)


def _rolling(x: np.ndarray, w: int, halves: bool = False) -> tuple[np.ndarray, ...]:
    """Centred rolling mean and std of the columns of x (N, K) over w samples (edges: shorter windows),
    and with ``halves`` the mean of each window's second half minus its first's (N, K): a slope
    estimate as good as the least-squares one within 14 % in its standard deviation, from the same sums.

    The sums run on x minus its first row, which keeps the variance free of cancellation when the
    gyro carries a large rate (a turn) beside a 0.002 deg/s noise. All columns at once: the
    cumulative sums run down each column in order, so every column's figures are those of the
    column on its own, bit for bit (tests/test_still_perf.py).
    """
    n = x.shape[0]
    x0 = x[0] if n else np.zeros(x.shape[1:])
    x = x - x0
    cs = np.empty((n + 1,) + x.shape[1:])
    cs[0] = 0.0
    np.cumsum(x, axis=0, out=cs[1:])
    cs2 = np.empty_like(cs)
    cs2[0] = 0.0
    np.cumsum(x * x, axis=0, out=cs2[1:])
    lo, hi = _window_bounds(n, w)
    cnt = (hi - lo)[:, None]
    mean = (cs[hi] - cs[lo]) / cnt
    var = np.maximum((cs2[hi] - cs2[lo]) / cnt - mean**2, 0.0)
    if not halves:
        return mean + x0, np.sqrt(var)
    mid = (lo + hi) // 2
    first = (cs[mid] - cs[lo]) / np.maximum(mid - lo, 1)[:, None]
    second = (cs[hi] - cs[mid]) / np.maximum(hi - mid, 1)[:, None]
    return mean + x0, np.sqrt(var), second - first


def rolling_stats(gyro: np.ndarray, accel: np.ndarray, w: int) -> np.ndarray:
    """Rolling statistics over w samples, a row (STATS_COLUMNS,) per sample: gyro mean [deg/s], gyro
    and accel std [deg/s, g], gyro and accel turn (the window's second-half mean minus its first's),
    and the std of the gyro's and accel's first and second differences (0 before the first sample),
    the accel mean [g], and the gyro's changes of value within the window [count]."""
    x = np.hstack([np.asarray(gyro, dtype=float), np.asarray(accel, dtype=float)])
    return _stats_rows(x, *_differences(x, None, None), w, slice(0, len(x)))


def _differences(x: np.ndarray, prev: np.ndarray | None,
                 prev_d1: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """First and second differences (N, 6) of rows x, continuing from the row before (``prev``) and
    its first difference (``prev_d1``); 0 where there is none."""
    d1 = np.zeros_like(x)
    if len(x):
        d1[1:] = np.diff(x, axis=0)
        if prev is not None:
            d1[0] = x[0] - prev
    d2 = np.zeros_like(x)
    if len(x):
        d2[1:] = np.diff(d1, axis=0)
        if prev_d1 is not None:
            d2[0] = d1[0] - prev_d1
    return d1, d2


def _stats_rows(x: np.ndarray, d1: np.ndarray, d2: np.ndarray, w: int, sel: slice) -> np.ndarray:
    """The STATS_COLUMNS rows ``sel`` of samples x (N, 6) and their differences d1, d2 (N, 6).

    x, d1 and d2 go through ``_rolling`` one at a time, the differences without halves: each column's
    figures are its own whatever runs beside it (``_rolling``), and the three together (N, 18) held
    about ten such arrays at once, 1.9 GB of a 3-hour 100 Hz log's analysis (over the issue's 2 GB
    with the rest: benchmarks/bench_analyze.py --long)."""
    out = np.empty((sel.stop - sel.start, STATS_COLUMNS))
    mean, std, halves = _rolling(x, w, halves=True)
    out[:, GYRO_MEAN] = mean[sel, 0:3]
    out[:, ACCEL_MEAN] = mean[sel, 3:6]
    out[:, 3:9] = std[sel]  # GYRO_STD, ACCEL_STD
    out[:, 9:15] = halves[sel]  # GYRO_TURN, ACCEL_TURN
    del mean, std, halves
    out[:, 15:21] = _rolling(d1, w)[1][sel]  # GYRO_D1, ACCEL_D1
    out[:, 21:27] = _rolling(d2, w)[1][sel]  # GYRO_D2, ACCEL_D2
    out[:, GYRO_CHANGES] = _changes(d1[:, 0:3], w)[sel]
    return out


def _changes(d1: np.ndarray, w: int) -> np.ndarray:
    """Per row and column of first differences d1 (N, K): how many times the value changes within the
    row's centred window of w samples [count], exactly (integer sums). A gyro axis that changes 0 times
    is stuck or railed: one at 2.0 deg/s with no noise was learnt as a 7,200 deg/h bias and pushed,
    and the record predicted 0.00002 deg/h left (an integrator's campaign, rc36a S1). Windows shorter
    than FLAT_MIN_WINDOW give NaN (not judged)."""
    n = d1.shape[0]
    if w < FLAT_MIN_WINDOW:
        return np.full(d1.shape, np.nan)
    cs = np.zeros((n + 1, d1.shape[1]), dtype=np.int64)
    np.cumsum(d1 != 0, axis=0, out=cs[1:])
    lo, hi = _window_bounds(n, w)
    # the changes between the window's own samples: differences lo+1 .. hi-1
    return (cs[hi] - cs[np.minimum(lo + 1, hi)]).astype(float)


def _slow(stats: np.ndarray, rule: StillRule) -> np.ndarray:
    """Per row (N,): the rolling gyro mean is within ``max_rate_dps`` along gravity (the rolling
    accelerometer mean, from 0.5 g), or on every axis where there is no such gravity (StillRule)."""
    g, a = stats[:, GYRO_MEAN], stats[:, ACCEL_MEAN]
    norm = np.linalg.norm(a, axis=1)
    has_g = np.isfinite(norm) & (norm > 0.5)
    along = np.abs(np.einsum("ij,ij->i", g, a)) / np.where(has_g, norm, 1.0)
    return np.where(has_g, along < rule.max_rate_dps, np.all(np.abs(g) < rule.max_rate_dps, axis=1))


def flat_axes(stats: np.ndarray) -> np.ndarray:
    """Per row and gyro axis (N, 3): the axis is flat in the row's window, a stuck or railed sensor:
    its value never changes, or its first differences spread less than FLAT_DPS times sqrt 2 (what
    a noise of FLAT_DPS gives). Never in a window shorter than FLAT_MIN_WINDOW (its count is NaN)."""
    changes = stats[:, GYRO_CHANGES]
    judged = np.isfinite(changes)
    return judged & ((changes <= 0) | (stats[:, GYRO_D1] < FLAT_DPS * np.sqrt(2.0)))


def quiet_levels(stats: np.ndarray, rule: StillRule, w: int,
                 accel_quantum_g: np.ndarray | None = None) -> QuietLevels:
    """The quiet level from rolling statistics rows (samples, or a decimated history of them).

    The accelerometer's quiet level is floored at half its quantum (``accel_quantum_g``, (3,) [g]): a
    quantised still axis (CAN: 1 mg) has a rolling std of exactly 0 in many windows, which would
    otherwise make nothing still. A turn's level (``w``: the window [samples]) is what the noise
    gives (``turn_noise``, from its differences, blind to a steady turn), floored like the spread: a
    quantised axis at white noise's 2 (quantum / 2) / sqrt(w).
    """
    live = ~np.any(flat_axes(stats), axis=1)
    if np.any(live):  # a stuck axis's windows would make its quiet level 0 (status showed 1e-09 deg/s)
        stats = stats[live]
    cols = np.r_[GYRO_STD, ACCEL_STD, GYRO_D1, ACCEL_D1, GYRO_D2, ACCEL_D2]
    q = np.full(STATS_COLUMNS, np.nan)
    q[cols] = np.quantile(stats[:, cols], rule.quantile, axis=0)  # per column, one call
    gq = np.maximum(q[GYRO_STD], 1e-9)
    floor = np.maximum(1e-6, 0.5 * (np.zeros(3) if accel_quantum_g is None else accel_quantum_g))
    aq = np.maximum(q[ACCEL_STD], floor)
    white = 2.0 / np.sqrt(max(w, 1))
    turn_dps = np.maximum(turn_noise(q[GYRO_D1], q[GYRO_D2], w), 1e-12)
    turn_g = np.maximum(turn_noise(q[ACCEL_D1], q[ACCEL_D2], w), white * floor)
    mean, std = stats[:, GYRO_MEAN], stats[:, GYRO_STD]
    centre = np.empty(3)
    slow = _slow(stats, rule)  # a turn never sets the centre
    for k in range(3):
        sel = (std[:, k] < rule.k_std * gq[k]) & slow
        centre[k] = np.median(mean[sel, k]) if np.any(sel) else 0.0
    return QuietLevels(gq, aq, centre, turn_g, turn_dps)


def quiet_mask(stats: np.ndarray, lv: QuietLevels, rule: StillRule) -> np.ndarray:
    """Per sample (N,): quiet by the rule's relative thresholds (before margins and minimum length)."""
    mean = stats[:, GYRO_MEAN]
    band = np.maximum(rule.band_k * lv.gyro_dps, rule.band_floor_dps)
    ok = np.all(stats[:, GYRO_STD] < rule.k_std * lv.gyro_dps, axis=1)
    ok &= np.all(np.abs(mean - lv.centre_dps) < band, axis=1)
    ok &= _slow(stats, rule)
    ok &= np.all(stats[:, ACCEL_STD] < rule.k_std * lv.accel_g, axis=1)
    ok &= np.all(np.abs(stats[:, ACCEL_TURN]) < rule.k_turn * lv.turn_g, axis=1)
    ok &= np.all(np.abs(stats[:, GYRO_TURN]) < rule.k_turn * lv.turn_dps, axis=1)
    ok &= ~np.any(flat_axes(stats), axis=1)
    if np.any(lv.gyro_dps > rule.max_quiet_dps):
        ok[:] = False
    return ok


def detect_still(
    columns: Mapping[str, np.ndarray], rate_hz: float, window_s: float = 0.4, k_std: float = 4.0,
    margin_s: float = 0.1, min_run_s: float = 0.5, rule: StillRule | None = None,
) -> np.ndarray:
    """A still mask (N,) from the gyro and accelerometer columns of a whole log (see ``StillRule``)."""
    if rule is None:
        rule = StillRule(window_s=window_s, k_std=k_std, margin_s=margin_s, min_run_s=min_run_s)
    n = len(columns["t"])
    if n == 0:
        return np.zeros(0, dtype=bool)
    gyro = np.column_stack([np.asarray(columns[f"w{a}"], dtype=float) for a in AXES])
    accel = np.column_stack([np.asarray(columns[f"a{a}"], dtype=float) for a in AXES])
    w = rule.window(rate_hz)
    stats = rolling_stats(gyro, accel, w)
    quantum = np.array([_quantum(accel[:, k]) for k in range(3)])
    ok = quiet_mask(stats, quiet_levels(stats, rule, w, quantum), rule)
    session = np.asarray(columns.get("session", np.zeros(n)))
    return _shrink(ok, session, rule.margin(rate_hz), rule.min_run(rate_hz))


def _quantum(x: np.ndarray) -> float:
    """The smallest step between distinct values (the quantisation LSB), from up to 200k samples.

    Steps between neighbours of the sorted values: the same steps as between the distinct values
    (``np.unique``), without building the distinct set.
    """
    steps = np.diff(np.sort(x[:200_000]))
    steps = steps[steps > 0]
    return float(steps.min()) if steps.size else 0.0


def _shrink(mask: np.ndarray, session: np.ndarray, margin: int, min_len: int) -> np.ndarray:
    """Shrink every true stretch by ``margin`` samples per end; drop those below ``min_len``."""
    out = np.zeros_like(mask)
    starts, ends = _stretches(mask, session)
    for s, e in zip(starts, ends, strict=True):
        s2, e2 = s + margin, e - margin
        if e2 - s2 >= max(min_len, 1):
            out[s2:e2] = True
    return out


def _stretches(mask: np.ndarray, session: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) indices of the true stretches of ``mask`` within sessions."""
    brk = np.concatenate(([True], session[1:] != session[:-1]))
    prev = np.concatenate(([False], mask[:-1])) & ~brk
    nxt_brk = np.concatenate((brk[1:], [True]))
    nxt = np.concatenate((mask[1:], [False])) & ~nxt_brk
    starts = np.flatnonzero(mask & ~prev)
    ends = np.flatnonzero(mask & ~nxt) + 1
    return starts, ends


class StreamingStill:
    """``detect_still`` for a stream: feed rows in blocks of any size, get back decided rows in order.

    Rows are any numpy structured array with fields wx, wy, wz [deg/s] and ax, ay, az [g] (the
    daemon's SAMPLE_DTYPE). Memory is bounded: a tail of undecided rows (look-ahead half a window,
    plus up to ``min_run_s`` + 2 ``margin_s`` while a stretch's length is unknown, plus ``learn_s``
    at switch-on) and a decimated history of ``memory_s`` for the quiet level. Decisions come out
    delayed by that look-ahead.
    """

    def __init__(self, rate_hz: float, rule: StillRule | None = None) -> None:
        self.rule = rule or StillRule()
        self.rate_hz = float(rate_hz)
        self.w = self.rule.window(self.rate_hz)
        self.ahead = self.w - self.w // 2 - 1  # rows after i inside i's window
        self.behind = self.w // 2
        self.margin = self.rule.margin(self.rate_hz)
        self.min_len = max(self.rule.min_run(self.rate_hz), 1)
        self.step = max(1, self.w // 4)  # history decimation
        hist = int(min(4096, max(64, self.rule.memory_s * self.rate_hz / self.step)))
        # rolling-statistics rows (STATS_COLUMNS), the newest ``hist``, in a circular buffer: the quiet
        # level is a quantile and a median over them, which do not depend on the rows' order
        self._hist = np.empty((hist, STATS_COLUMNS))
        self._hist_n = 0  # rows held
        self._hist_i = 0  # where the next row goes
        self._learn_rows = int(round(self.rule.learn_s * self.rate_hz))
        self.levels: QuietLevels | None = None
        self.seen = 0  # rows fed
        self.decided = 0  # rows returned
        self.still_decided = 0
        self._rows: np.ndarray | None = None  # look-behind + rows whose statistics are pending
        self._stat_from = 0  # index in _rows of the first row without statistics
        self._stat_index = 0  # global index of that row
        self._pending_rows: list[np.ndarray] = []  # rows with statistics, waiting for levels
        self._pending_stats: list[np.ndarray] = []
        self._q_rows: np.ndarray | None = None  # rows with quiet flags, waiting for the run rule
        self._q_ok = np.zeros(0, dtype=bool)
        self._q0 = 0  # global index of _q_rows[0]
        self._run_start: int | None = None  # global start of the stretch open at _q_rows[0]
        self._empty: np.ndarray | None = None
        self._levels_at = -(1 << 62)  # _stat_index when the levels were last computed
        self._quantum = np.full(3, np.inf)  # smallest accel step seen per axis [g] (quantisation)
        self._prev: np.ndarray | None = None  # the row before the kept look-behind (differences)
        self._prev_d1: np.ndarray | None = None  # its first difference
        self.flat_rows = np.zeros(3, dtype=np.int64)  # rows judged whose gyro axis had no noise (flat_axes)
        self.flat_now = np.zeros(3, dtype=bool)  # ... per axis, at the newest row judged
        self.flat_value_dps = np.zeros(3)  # the newest row judged's gyro reading [deg/s]

    def reset(self) -> None:
        self.__init__(self.rate_hz, self.rule)  # type: ignore[misc]

    @property
    def still_fraction(self) -> float:
        return self.still_decided / self.decided if self.decided else 0.0

    def feed(self, block: np.ndarray, final: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Return (decided rows, still mask); ``final`` decides everything left (end of a log)."""
        self.seen += block.size
        if self._empty is None:
            self._empty = block[:0]
        rows = block if self._rows is None else np.concatenate([self._rows, block])
        self._rows = rows
        n = rows.size
        upto = n if final else n - self.ahead  # rows [_stat_from, upto) now have full windows
        if upto > self._stat_from and n:
            lo = max(0, self._stat_from - self.behind)
            part = rows[lo:n]
            x = np.empty((part.size, 6))
            for k, f in enumerate(_FIELDS):
                x[:, k] = part[f]
            for k in range(3):
                self._quantum[k] = min(self._quantum[k], _quantum(x[:, 3 + k]) or np.inf)
            # differences, continuing from the row before the part (0 at the start)
            d1, d2 = _differences(x, self._prev, self._prev_d1)
            # centred windows: rows before _stat_from are kept as look-behind for this purpose
            stats = _stats_rows(x, d1, d2, self.w, slice(self._stat_from - lo, upto - lo))
            self._pending_rows.append(rows[self._stat_from:upto])
            self._pending_stats.append(stats)
            first = self._stat_index
            self._add_history(stats[(-first) % self.step::self.step])
            self._stat_index += upto - self._stat_from
            keep = max(0, upto - self.behind)
            if keep > 0:  # the row before those kept, and its first difference
                self._prev, self._prev_d1 = x[keep - 1 - lo].copy(), d1[keep - 1 - lo].copy()
            self._rows = rows[keep:]
            self._stat_from = upto - keep
        if self.levels is None and self._stat_index < self._learn_rows and not final:
            return self._emit(final=False)
        if self._pending_stats:
            if self._stat_index - self._levels_at >= max(1, self.rate_hz * 0.25) or final:
                h = self._hist[:self._hist_n] if self._hist_n else np.vstack(self._pending_stats)
                quantum = np.where(np.isfinite(self._quantum), self._quantum, 0.0)
                self.levels = quiet_levels(h, self.rule, self.w, quantum)
                self._levels_at = self._stat_index
            assert self.levels is not None
            st = np.vstack(self._pending_stats)
            ok = quiet_mask(st, self.levels, self.rule)
            prs = np.concatenate(self._pending_rows)
            flat = flat_axes(st)
            self.flat_rows += flat.sum(axis=0)
            if prs.size:
                self.flat_now = flat[-1]
                self.flat_value_dps = np.array([float(prs[f][-1]) for f in _FIELDS[:3]])
            self._pending_rows, self._pending_stats = [], []
            self._q_rows = prs if self._q_rows is None else np.concatenate([self._q_rows, prs])
            self._q_ok = np.concatenate([self._q_ok, ok])
        return self._emit(final)

    def _add_history(self, rows: np.ndarray) -> None:
        """Keep the newest ``len(self._hist)`` decimated statistics rows (a bounded memory)."""
        cap = self._hist.shape[0]
        rows = rows[-cap:]
        m = rows.shape[0]
        i = self._hist_i
        first = min(m, cap - i)
        self._hist[i:i + first] = rows[:first]
        self._hist[:m - first] = rows[first:]
        self._hist_i = (i + m) % cap
        self._hist_n = min(cap, self._hist_n + m)

    def _emit(self, final: bool) -> tuple[np.ndarray, np.ndarray]:
        """Apply margins and the minimum length to the queued quiet flags; return the decided prefix.

        Only the last stretch can be undecided: its rows within ``margin`` of the queue's end (it
        may go on), or all its rows after the start margin while its length is below ``min_run``.
        """
        ok = self._q_ok
        n = ok.size
        if self._q_rows is None or n == 0:
            return self._empty, np.zeros(0, dtype=bool)
        still = np.zeros(n, dtype=bool)
        decided = n
        open_start: int | None = None
        starts, ends = _stretches(ok, np.zeros(n))
        m = self.margin
        for s, e in zip(starts, ends, strict=True):
            gs = self._run_start if (s == 0 and self._run_start is not None) else self._q0 + s
            lo_i = gs + m - self._q0  # queue index of the first row past the start margin
            long_enough = self._q0 + e - gs - 2 * m >= self.min_len
            if e < n or final:
                if long_enough:
                    still[max(lo_i, 0):max(e - m, 0)] = True
                continue
            open_start = gs
            if long_enough:
                still[max(lo_i, 0):max(n - m, 0)] = True
                decided = min(max(n - m, 0), n)
            else:
                decided = min(max(lo_i, s, 0), n)
        out_rows, out = self._q_rows[:decided], still[:decided]
        self._run_start = open_start
        self._q_rows = self._q_rows[decided:]
        self._q_ok = ok[decided:]
        self._q0 += decided
        self.decided += decided
        self.still_decided += int(out.sum())
        return out_rows, out
