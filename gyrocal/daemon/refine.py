"""The push gate's rule, per axis, for a first set and for a refinement of the set a unit holds.

Why (issue 10): the gate used to ask, on EVERY axis, that the new set's predicted drift left be
below 1/``min_cut`` of the drift it removes. Right for a first set (the unit holds nothing useful,
so every axis must gain). Wrong for a refinement: once the held set is good on one axis, that axis's
change stays small, and it blocked a second, wider set that the other axes (or the temperature range)
needed. A warm-up that gave a first push over 22-33 degC then kept that narrow set for good, and the
autopilot clamps its temperature into TMIN..TMAX above it.

The rule, with ``left`` the new set's predicted drift left [deg/s] (3,), ``removes`` the drift it
would take out of the present output at the poses seen (3,), and ``held_left`` the held set's own
predicted drift left when it was pushed (3,; zeros for a set the daemon did not push):

- an axis **gains** when ``left <= target`` or ``left * cut <= removes`` (the held set is off on it by
  ``cut`` times the new set's own uncertainty; ``cut`` is ``push.min_cut``, 20), or, on a unit that
  holds a set, ``left * HELD_CUT <= removes`` (4: a first push of a unit that holds nothing keeps 20);
- an axis is **not made worse** when it gains, or ``left <= NOT_WORSE_RATIO * max(held_left,
  removes)``: the new set is predicted about as accurate as the held set was when it was pushed, or
  the held set is off by more than the new set's uncertainty. The ratio (2) is there because the two
  figures are over different poses: ``held_left`` over the narrower range the held set saw,
  ``left`` over the wider range now seen, whose new, steeper end is the least determined part; with
  1, a warm-up's last, end-of-range set was refused in some runs. The held-out check per axis
  (``axes_not_worse``) is the measured guard;
- the set passes when every axis is not made worse and (some axis gains, or the temperature range
  seen has widened beyond the held set's: ``widened``). Once the warm-up has settled, a widening of a
  tenth of a degree counts where the held set leaves more than 1/``cut`` of the unit's drift at the
  new end (``edge_costs``): an autopilot clamps into TMAX, and its steepest axis pays slope x gap.

A unit whose bias wanders (the ``kf`` estimator with a spec from ``gyrocal analyze``: a random walk,
a flicker floor) has a ``floor``: the drift the wander leaves over ``push.wander_horizon_s`` whatever
set is pushed (bias_kalman.BiasKalman.wander_dps). ``left * cut <= removes`` may then never come: on a
tactical MEMS unit (0.05 deg/s per sample at 100 Hz, B 10 deg/h, walk 21.6 deg/h/sqrt(h)) the predicted
drift left was 6 deg/h after 25 minutes, against 14-22 deg/h removed, and 1/20 of that takes hours of
rests, while the unit ran uncalibrated. There an axis also **gains** when learning longer cannot buy
much (``left <= WANDER_LEFT_SHARE * floor``: the total left, hypot(left, floor), is within 12 % of the
floor) and the push is worth making (hypot(left, floor) is at most ``1 - min_improvement`` of
hypot(removes, floor), the drift the unit keeps without it: validation's own ratio).

For a unit that holds no set of ours (``held_left`` zero, no recorded range) this is the old rule:
every axis must gain. Validation on held-out blocks still follows (session.py), and for a refinement
it also checks each axis on its own (``axes_not_worse``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WIDEN_FRACTION = 0.25
"""While the temperature moves, the range seen must exceed the held set's by this fraction of the held
width (and WIDEN_MIN_C) for a refinement on the range alone: a warm-up then gives a few pushes, each
about a quarter wider, not one every degree..."""
WIDEN_MIN_C = 1.0
"""...and by at least this many degC."""
SETTLED_MIN_C = 0.5
"""Once the temperature has settled (|dT/dt| below SETTLED_C_PER_S), a widening by this many degC
suffices: the end of a warm-up, where the thermal curve is often steepest and a clamp costs most
(0.5 degC x 115 deg/h/degC = 60 deg/h on the virtual ArduPilot's steepest axis)."""
EDGE_MIN_C = 0.1
"""[degC] Once settled, the least widening that counts when the held set leaves more than 1/cut of the
unit's drift at the new end (``edge_costs``): on the virtual ArduPilot's steepest axis (115
deg/h/degC, 670 deg/h of drift) 1/20 is reached 0.3 degC past TMAX, where SETTLED_MIN_C alone left
0.5 degC x 115 = 58 deg/h (8.2x over the whole range seen, bench_mavlink.py seed 2). This floor
bounds the flash writes on a flat curve that the ratio alone would not."""
SETTLED_C_PER_S = 0.02
"""[degC/s] A warm-up counts as settled below this rate (1.2 degC/min)..."""
SETTLED_FRACTION = 0.1
"""...and below this fraction of the fastest rate seen since the switch-on: for an exponential warm-up,
90 % of the rise is done. Without it a slow warm-up (time constant 10 min, 0.05 degC/s at its fastest)
counted as settled at 38 of 50 degC and gave a push every degree after that (16 pushes in 30 min in
the harness; 10 with it)."""


def settled(rate_c_per_s: float, peak_c_per_s: float) -> bool:
    """True when the temperature rate [degC/s] says the warm-up has (nearly) settled."""
    r = abs(rate_c_per_s)
    return r < SETTLED_C_PER_S and r <= SETTLED_FRACTION * abs(peak_c_per_s)
KEPT_GAIN = 3.0
"""On an axis whose held bias was kept from an older set (module docstring of ``gate``), a refinement
gains when it leaves 1/KEPT_GAIN of the held set's predicted drift there: a kept y/z whose bias had
moved 21-25 deg/h was never refined, a full set leaving 5-6 deg/h falling short of 1/20 of the 21-26
it removed (a serial integrator's re-check)."""
HELD_CUT = 4.0
"""On a unit that holds a set (a refinement, or a full set over a held set's bias stage), an axis also
gains when the drift the new set removes is HELD_CUT times its predicted drift left: the held set is
off there by 4x the new set's uncertainty, so a prediction that misses by 2x still halves the axis's
drift. With ``cut`` (20) alone, a tumbling unit whose gravity terms had moved 3 deg/h was left at
3.9/3.5/5.7 deg/h to the end of a 110 s run, its status saying the new set would leave 0.6 of the
3.1-6.1 deg/h it removes: 1/20 of that takes 25 minutes of rests (an integrator's campaign, rc33 G2).
A held set that is right gives ``removes`` about equal to ``left`` (the new set's own error), so
this does not push again and again: the next refinement needs the drift left 4x lower, 16x the samples.
A unit that holds nothing keeps ``cut`` on every axis (a first push cuts every axis 10x: issue 9)."""
NOT_WORSE_RATIO = 2.0
"""How much larger than the held set's a refinement's predicted drift left may be on an axis that does
not gain (see the module docstring)."""
AXIS_TOLERANCE = 0.05
"""A refinement's held-out RMS may exceed the held set's on an axis by at most this fraction (the
blocks are the same for both sets, so their noise is common: the difference is the sets')."""


WANDER_LEFT_SHARE = 0.5
"""With a wandering bias, an axis gains once its predicted drift left is at most this share of the
wander's floor (module docstring): hypot(0.5, 1) = 1.118, so waiting could cut the total by 11 % at best."""


@dataclass(frozen=True)
class GateResult:
    """The gate's decision, with the per-axis masks it was made from."""

    ok: bool
    gains: np.ndarray  # (3,) bool
    not_worse: np.ndarray  # (3,) bool
    widened: bool
    floor: np.ndarray | None = None  # the wander's drift the gate weighed [deg/s] (3,), if any


def gate(left: np.ndarray, removes: np.ndarray, target_dps: float, cut: float,
         held_left: np.ndarray | None = None, widened: bool = False,
         floor: np.ndarray | None = None, min_improvement: float = 0.2,
         kept: np.ndarray | None = None, holds_set: bool = False) -> GateResult:
    """The rule of the module docstring; all figures per axis in deg/s (``floor``: None, or the
    wander's drift (3,) that no set removes). ``kept`` (3,) bool: axes on which the held set kept an
    older set's bias (a bias stage, ``kept_axes``): such an axis also gains when the new set's drift
    left is at most 1/KEPT_GAIN of the held set's there, which holds the bias's move. ``holds_set``: the
    unit holds a set (any version above 0, known to the store or not): an axis also gains at HELD_CUT."""
    left = np.asarray(left, dtype=float)
    removes = np.nan_to_num(np.asarray(removes, dtype=float), nan=0.0)
    held = np.zeros(3) if held_left is None else np.nan_to_num(np.asarray(held_left, dtype=float))
    finite = bool(np.all(np.isfinite(left)))
    with np.errstate(invalid="ignore"):
        gains = (left <= target_dps) | (left * cut <= removes)
        if floor is not None:
            f = np.nan_to_num(np.asarray(floor, dtype=float), nan=0.0)
            gains |= (f > 0) & (left <= WANDER_LEFT_SHARE * f) \
                & (np.hypot(left, f) <= (1.0 - min_improvement) * np.hypot(removes, f))
        if kept is not None:
            gains |= np.asarray(kept, dtype=bool) & (held > 0) & (left * KEPT_GAIN <= held)
        if holds_set:
            gains |= left * min(cut, HELD_CUT) <= removes
        not_worse = gains | (left <= NOT_WORSE_RATIO * np.maximum(held, removes))
    if not np.any(held > 0):  # a held set the daemon knows nothing about: every axis must gain
        ok = finite and bool(np.all(gains))
    else:
        ok = finite and bool(np.all(not_worse)) and (bool(np.any(gains)) or widened)
    kept = None if floor is None else np.asarray(floor, dtype=float)
    return GateResult(ok, gains, not_worse, widened, kept)


def widened(held_range: tuple[float, float] | None, seen: tuple[float, float] | None,
            settled: bool = False, edge_costs: bool = False) -> bool:
    """True when the range seen [degC] reaches beyond the held set's by WIDEN_FRACTION of its width
    (and WIDEN_MIN_C), or, once the temperature has ``settled``, by SETTLED_MIN_C, or by EDGE_MIN_C
    where ``edge_costs`` (``edge_costs``: the drift the held set leaves there is worth a push);
    False when either range is unknown."""
    if held_range is None or seen is None:
        return False
    lo, hi = held_range
    ext = max(0.0, lo - seen[0]) + max(0.0, seen[1] - hi)
    if settled:
        return ext >= SETTLED_MIN_C or (edge_costs and ext >= EDGE_MIN_C)
    return ext >= max(WIDEN_MIN_C, WIDEN_FRACTION * (hi - lo))


def edge_temps(held_range: tuple[float, float] | None,
               seen: tuple[float, float] | None) -> list[float]:
    """The ends [degC] of the range seen that lie beyond the held set's range (none if unknown)."""
    if held_range is None or seen is None:
        return []
    return [t for t, out in ((seen[0], seen[0] < held_range[0]), (seen[1], seen[1] > held_range[1])) if out]


def edge_costs(edge_left: np.ndarray, drift: np.ndarray, cut: float) -> bool:
    """True when, on some axis, the drift the held set leaves at an end of the range seen beyond its
    own (``edge_left`` [deg/s] (3,)) is more than 1/``cut`` of the drift the unit has uncompensated
    (``drift`` [deg/s] (3,), RMS over the poses seen): the push gate's own ratio, applied to the part
    of the range the held set does not cover."""
    e = np.nan_to_num(np.asarray(edge_left, dtype=float), nan=0.0)
    d = np.nan_to_num(np.asarray(drift, dtype=float), nan=np.inf)
    return bool(np.any(e * cut > d))


def axes_not_worse(rms_old: np.ndarray, rms_new: np.ndarray, tol: float = AXIS_TOLERANCE) -> np.ndarray:
    """Per axis (3,) bool: the new set's held-out RMS [deg/s] is within ``tol`` of the held set's."""
    return np.asarray(rms_new) <= np.asarray(rms_old) * (1.0 + tol)
