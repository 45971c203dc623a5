"""Units of the quantities in a log, and their conversion to deg/s, g, degC and s.

Every reader delivers gyro in deg/s, specific force in g, temperature in degC and time in s (the
units the estimators' coefficients are expressed in, docs/logformat.md). A CSV declares what it
holds in a ``# units: gyro=rad/s accel=m/s^2`` line or with ``--units``; foreign formats (ULog,
DataFlash, ROS) carry SI units that their readers convert.

Wrong units do not fail loudly on their own: a log with rad/s and m/s^2 read as deg/s and g gives
coefficients 57x too small and still "converges". Hence ``looks_like_si``: at rest the specific
force has a norm of 1 g; a median norm near 9.8 means m/s^2, and the reader warns.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from gyrocal.errors import ConfigError

G0 = 9.80665
"""Standard gravity [m/s^2] (the g of the accel columns)."""

FACTORS: dict[str, dict[str, float]] = {
    "gyro": {"deg/s": 1.0, "dps": 1.0, "rad/s": 180.0 / math.pi, "mrad/s": 0.18 / math.pi,
             "deg/h": 1.0 / 3600.0},
    "accel": {"g": 1.0, "m/s^2": 1.0 / G0, "m/s2": 1.0 / G0, "m/s/s": 1.0 / G0, "mg": 1e-3},
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9},
    "temp": {"degC": 1.0, "C": 1.0, "K": 1.0, "degF": 5.0 / 9.0},
}
"""Multiply a value in the named unit by this factor to get the canonical unit."""
OFFSETS = {("temp", "K"): -273.15, ("temp", "degF"): -32.0 * 5.0 / 9.0}
"""Added after the factor (temperature scales with an offset)."""
COLUMNS = {"gyro": ("wx", "wy", "wz", "ref_wx", "ref_wy", "ref_wz"), "accel": ("ax", "ay", "az"),
           "time": ("t",), "temp": ("temp",)}
ALIASES = {"accelerometer": "accel", "acc": "accel", "rate": "gyro", "t": "time", "temperature": "temp"}


def parse_units(text: str, where: str = "--units") -> dict[str, str]:
    """``gyro=rad/s,accel=m/s^2`` (commas or spaces) -> {"gyro": "rad/s", "accel": "m/s^2"}.

    ConfigError names the bad item and lists the known quantities and units.
    """
    out: dict[str, str] = {}
    for item in text.replace(",", " ").split():
        qty, sep, unit = item.partition("=")
        qty = ALIASES.get(qty.strip().lower(), qty.strip().lower())
        unit = unit.strip()
        if not sep or qty not in FACTORS:
            raise ConfigError(f"{where}: {item!r} is not QUANTITY=UNIT; quantities: {', '.join(FACTORS)} "
                              "(e.g. gyro=rad/s,accel=m/s^2)")
        if unit not in FACTORS[qty]:
            raise ConfigError(f"{where}: unit {unit!r} unknown for {qty}; use one of "
                              f"{', '.join(FACTORS[qty])}")
        out[qty] = unit
    return out


def declared_units(text: str, where: str) -> dict[str, str]:
    """The units of a ``# units:`` metadata line ({} when the line is absent or empty)."""
    return parse_units(text, where) if text.strip() else {}


def convert_columns(columns: dict[str, np.ndarray], units: Mapping[str, str]) -> None:
    """Convert the named quantities' columns in place to deg/s, g, degC and s."""
    for qty, unit in units.items():
        factor, offset = FACTORS[qty][unit], OFFSETS.get((qty, unit), 0.0)
        if factor == 1.0 and offset == 0.0:
            continue
        for c in COLUMNS[qty]:
            if c in columns:
                columns[c] = np.asarray(columns[c], dtype=np.float64) * factor + offset


def looks_like_si(log: object) -> str | None:
    """A warning when the accel columns [g] look like m/s^2 (median norm 4..20), else None.

    Why the median norm: at rest the specific force is 1 g whatever the attitude, and a vehicle
    spends most of a calibration log near rest; 4..20 leaves room for vibration and for a log in
    units of g that is mostly manoeuvring (whose norm stays well below 4 g on a median).
    """
    cols = log.columns  # type: ignore[attr-defined]
    if cols["ax"].size == 0:
        return None
    norm = float(np.median(np.sqrt(cols["ax"] ** 2 + cols["ay"] ** 2 + cols["az"] ** 2)))
    if 4.0 <= norm <= 20.0:
        return (f"{getattr(log, 'source', 'log')}: the accel norm's median is {norm:.2f}, which looks like "
                "m/s^2 where g is expected (and gyro may then be rad/s, not deg/s); if so, pass "
                "--units accel=m/s^2,gyro=rad/s or write '# units: gyro=rad/s accel=m/s^2' in the "
                "header (docs/logformat.md)")
    return None


RAD_CHECK_ROWS = 200_000
"""Rows of a log the gyro units check looks at (its first moves are enough)."""


def gyro_units_warning(log: object) -> str | None:
    """A warning when the gyro columns [deg/s] look like rad/s: across the moves between rests, the
    gyro's integrated rate is under a tenth of the turn the accelerometer shows, else None.

    Why: rad/s read as deg/s made every figure 57x too small with no word, on a tumble log whose accel
    was in g (an outside check). The integral of |w| over a move is at least the angle between the
    gravity directions of the rests either side, whatever the path; a ratio near 1/57 is the unit. A
    move the log did not sample (a gap) says nothing and is skipped; so is a static log.
    """
    from gyrocal.model.still import detect_still, sample_rate_hz  # late: the reader needs it only here

    cols = log.columns  # type: ignore[attr-defined]
    if any(c not in cols for c in ("t", "wx", "wy", "wz", "ax", "ay", "az")) or cols["t"].size < 200:
        return None
    sub = {k: np.asarray(v[:RAD_CHECK_ROWS], dtype=np.float64) for k, v in cols.items()
           if k in ("t", "wx", "wy", "wz", "ax", "ay", "az", "session")}
    sub.setdefault("session", np.zeros(sub["t"].size))
    # rows no sensor gives are dropped after reading (readers/plausible.py); here, one rate of 1e300
    # deg/s overflowed the still detector's sums and left the check nothing (rc36b M4)
    from gyrocal.readers.plausible import within_range

    ok = within_range(sub)
    if not ok.all():
        sub = {k: v[ok] for k, v in sub.items()}
    t, session = sub["t"], sub["session"]
    if not np.all(np.isfinite(t)):
        return None
    rate = sample_rate_hz(t, session)
    still = detect_still(sub, rate)
    edges = np.flatnonzero(np.diff(still.astype(np.int8)))
    acc = np.column_stack([sub["ax"], sub["ay"], sub["az"]])
    w = np.sqrt(sub["wx"] ** 2 + sub["wy"] ** 2 + sub["wz"] ** 2)
    ratios = []
    # edges: k where still[k] != still[k + 1]; a move runs from a rest's last sample to the next's first
    leave = edges[0::2] if still[0] else edges[1::2]
    arrive = edges[1::2] if still[0] else edges[2::2]
    for a, b in zip(leave, arrive, strict=False):
        i, j = int(a), int(b) + 1  # last still sample before the move, first one after it
        if j >= t.size or session[i] != session[j] or np.max(np.diff(t[i:j + 1])) > 5.0 / rate:
            continue
        g1 = acc[max(0, i - int(0.2 * rate)):i + 1].mean(axis=0)
        g2 = acc[j:j + int(0.2 * rate) + 1].mean(axis=0)
        cosang = float(np.dot(g1, g2) / max(np.linalg.norm(g1) * np.linalg.norm(g2), 1e-12))
        turn = math.degrees(math.acos(min(1.0, max(-1.0, cosang))))
        if turn < 20.0:
            continue
        ratios.append(float(np.sum(w[i:j] * np.diff(t[i:j + 1]))) / turn)
    if len(ratios) >= 3 and float(np.median(ratios)) < 0.1:
        return (f"{getattr(log, 'source', 'log')}: across {len(ratios)} moves the gyro integrates to "
                f"{float(np.median(ratios)):.3f} of the turn the accelerometer shows (1 if deg/s; 0.017 if "
                "rad/s): the gyro looks like rad/s where deg/s is expected; if so, pass --units gyro=rad/s "
                "or write '# units: gyro=rad/s' in the header (docs/logformat.md)")
    return None


def temperature_units_warning(log: object) -> str | None:
    """A warning when the temp column [degC] looks like kelvin or Fahrenheit, else None.

    Why: a log in K was read as 298 degC with no word (a foreign-log audit). An IMU's die
    temperature lies within -55..125 degC; a median above 150 is not degC. K (about 220..420) is told
    from F by nothing but range, so both are named, and the fix is the units flag.
    """
    cols = log.columns  # type: ignore[attr-defined]
    temp = cols.get("temp")
    if temp is None or np.size(temp) == 0:
        return None
    med = float(np.nanmedian(temp))
    if not np.isfinite(med) or med <= 150.0:
        return None
    guess = "kelvin" if 200.0 <= med <= 450.0 else "not degC"
    return (f"{getattr(log, 'source', 'log')}: the temperature's median is {med:.1f}, which looks like "
            f"{guess} where degC is expected; if so, pass --units temp=K (or temp=degF) or write "
            "'# units: temp=K' in the header (docs/logformat.md)")


def time_units_warning(log: object) -> str | None:
    """A warning when the time column [s] looks like ms, us or ns, else None.

    Why: a 100 Hz log with its time in ms was read at 0.1 Hz with no word (a foreign-log audit). An
    IMU log's median sample interval is well under 0.5 s; above that the time is in a finer unit.
    """
    t = log.columns.get("t")  # type: ignore[attr-defined]
    if t is None or np.size(t) < 3:
        return None
    dt = np.diff(np.asarray(t, dtype=np.float64))
    dt = dt[np.isfinite(dt) & (dt > 0)]
    if dt.size == 0:
        return None
    med = float(np.median(dt))
    if med <= 0.5:
        return None
    guess = "ms" if med < 500.0 else "us" if med < 5e5 else "ns"
    return (f"{getattr(log, 'source', 'log')}: the median sample interval is {med:.3g} s "
            f"({1.0 / med:.3g} Hz), which looks like a time column in {guess}; if so, pass --units "
            f"time={guess} or write '# units: time={guess}' in the header (docs/logformat.md)")


def units_warnings(log: object, declared: Mapping[str, str] | None = None) -> list[str]:
    """Every units warning for a log's columns (accel, temperature, time, gyro): what the whole-file and
    the streaming CSV readers both add. A time unit the file or the user declared (``declared``) is
    taken as said: gyrocal convert's own 2 Hz ArduSub log, whose header says time=s, was warned of as
    "looks like ms" (an outside check); a slow log in seconds and a fast one in ms overlap near 1 s."""
    time_said = bool(declared) and "time" in declared
    found = (looks_like_si(log), temperature_units_warning(log),
             None if time_said else time_units_warning(log), gyro_units_warning(log))
    return [w for w in found if w]

