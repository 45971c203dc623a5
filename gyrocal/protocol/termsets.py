"""Term sets the unit knows, named on the wire by a 16-bit terms_id.

A coefficient set only means something with its term list: coefficient k of an axis multiplies term
k. Sending the names would cost a frame per term on CAN, so both sides hash the canonical list
instead: terms_id = CRC-16/CCITT-FALSE (binascii.crc_hqx, init 0xFFFF) of the names, spaces removed,
joined by "," and encoded as ASCII. The unit holds a table of the sets its firmware can evaluate and
NAKs an unknown id with UNKNOWN_TERMS, so a host can never make it apply coefficients to the wrong
terms.
"""

from __future__ import annotations

import binascii
from collections import deque
from collections.abc import Iterable

import numpy as np

from gyrocal.errors import ConfigError, ProtocolError
from gyrocal.model.terms import SEED000_TERMS, TermSpec
from gyrocal.protocol.messages import SEQ_MODULO

EXTENDED_TEMP_TERMS: tuple[str, ...] = SEED000_TERMS + ("temp", "temp^2", "dtemp", "temp*dtemp")
"""Seed 000's ten gravity terms plus temperature level [degC] and rate [degC/s] terms."""

_REGISTRY: dict[int, tuple[str, ...]] = {}


def canonical(names: Iterable[str]) -> tuple[str, ...]:
    """Names with spaces removed, in the given order (order matters: it fixes coefficient order)."""
    out = tuple(str(n).replace(" ", "") for n in names)
    if not out or any(not n or "," in n for n in out):
        raise ProtocolError(f"term names {out!r} must be non-empty and contain no commas")
    return out


def terms_id(names: Iterable[str]) -> int:
    """The 16-bit id of a term list: CRC-16/CCITT-FALSE over the comma-joined canonical names."""
    text = ",".join(canonical(names))
    try:
        data = text.encode("ascii")
    except UnicodeEncodeError as err:
        raise ProtocolError(f"term names {text!r} must be ASCII") from err
    return binascii.crc_hqx(data, 0xFFFF)


UNIT_ATOMS = ("gx", "gy", "gz", "temp", "dtemp", "t_on")
"""The atoms a unit evaluates per sample (protocol.md, section 4), besides exp(-t_on/TAU), sin(F) and
cos(F). The analysis may fit other columns; a unit's set may not use them."""


def foreign_atoms(names: Iterable[str]) -> list[str]:
    """The atoms of ``names`` that no unit evaluates (protocol.md, section 4), in order, each once;
    ConfigError on a malformed name."""
    out: list[str] = []
    for term in TermSpec.parse(list(names)).terms:
        for f in term.factors:
            ok = f.atom in UNIT_ATOMS or f.atom.startswith(("exp(", "sin(", "cos("))
            if not ok and f.atom not in out:
                out.append(f.atom)
    return out


def register_unit_terms(names: Iterable[str]) -> int:
    """Register a set a unit is to evaluate (the daemon's ``estimator.terms``, `gyrocal sim --terms`)
    and return its id. ConfigError when a name is malformed, uses an atom no unit evaluates (a column
    only the analysis has) or collides with another set's id; the caller names where it came from."""
    names = list(names)
    foreign = foreign_atoms(names)
    if foreign:
        raise ConfigError(f"{', '.join(map(repr, foreign))} is not an atom a unit evaluates; build terms "
                          f"from {', '.join(UNIT_ATOMS)}, exp(-t_on/TAU), sin(F) and cos(F) "
                          "(docs/protocol.md, section 4)")
    try:
        return register(names)
    except ProtocolError as err:
        raise ConfigError(str(err)) from None


def register(names: Iterable[str]) -> int:
    """Add a term set to the registry and return its id; a hash collision raises ProtocolError."""
    canon = canonical(names)
    tid = terms_id(canon)
    known = _REGISTRY.get(tid)
    if known is not None and known != canon:
        raise ProtocolError(f"terms_id 0x{tid:04X} of {canon!r} collides with {known!r}; rename a term")
    _REGISTRY[tid] = canon
    return tid


def names_for(tid: int) -> tuple[str, ...] | None:
    """The term names registered under tid, or None when the id is unknown."""
    return _REGISTRY.get(tid)


def known_ids() -> dict[int, tuple[str, ...]]:
    """A copy of the registry (id -> names), e.g. for a unit's table or docs."""
    return dict(_REGISTRY)


SEED000_ID = register(SEED000_TERMS)
EXTENDED_TEMP_ID = register(EXTENDED_TEMP_TERMS)
TEMP_POLY3_TERMS: tuple[str, ...] = ("1", "temp", "temp^2", "temp^3")
"""A cubic polynomial in temperature [degC] per axis: what PX4 (TC_G*) and ArduPilot (INS_TCAL*) hold."""
TEMP_POLY3_ID = register(TEMP_POLY3_TERMS)
TEMP_POLY2_ID = register(TEMP_POLY3_TERMS[:3])
"""The quadratic and linear prefixes: an autopilot holds them too (the higher coefficients are 0)."""
TEMP_POLY1_ID = register(TEMP_POLY3_TERMS[:2])


class TempRate:
    """``dtemp`` [degC/s] exactly as a unit computes it for a term set that uses it (protocol.md, section 6).

    Each whole second of unit time (floor(t_s)) the unit averages the temperature of that second's
    samples. When a second closes, dtemp becomes the least-squares slope of the last 20 such means
    against their second's mid-time (0 until 3 means exist). A sample uses the dtemp in force when it
    was taken, i.e. from the seconds before its own. Both the unit and the host's reconstruction of
    the unit's compensation use this one rule, so their ``dtemp`` agree sample for sample.
    """

    WINDOW = 20

    def __init__(self) -> None:
        self._sec: int | None = None
        self._sum = 0.0
        self._n = 0
        self._means: deque[tuple[float, float]] = deque(maxlen=self.WINDOW)
        self.value = 0.0
        self._dirty: int | None = None  # the last whole second this copy saw only in part
        self._last: tuple[int, float, float] | None = None  # seq, t [s], temp [degC] of the last sample
        self._dt: float | None = None  # [s] the unit's sample interval, from samples received in a row

    FILL_S = 2.0
    """Longest gap [s of unit time] whose lost samples are filled in: their temperatures by a straight
    line between the samples on either side, their times on the unit's sample clock. The unit's means
    then differ from the host's only by the lost samples' noise and the temperature's curvature over
    the gap (at most FILL_S^2 / 8 times |d2T/dt2|: 4e-3 degC over 2 s of a warm-up that starts at
    0.5 degC/s with a 60 s time constant, which moves dT/dt by about 1e-4 degC/s once the window
    holds 20 means). Such a copy still counts as the unit's: a link that loses a burst every few seconds
    (a USB-serial adapter that overruns, a busy CAN bus) would otherwise keep a unit with a dT/dt set
    out of learning for good (benchmarks/bench_late_start.py --cases lossy). A longer gap leaves the
    seconds around it seen in part, for WINDOW seconds."""

    @property
    def exact(self) -> bool:
        """Whether ``value`` is the unit's own: every second in the window was seen whole.

        A host that starts on a running unit (or reads its set a moment after the HELLO) averages a
        part of its first second only, and for the next WINDOW seconds its dtemp is not the unit's:
        during a warm-up the difference times a held dtemp coefficient is a drift the host would
        learn. Seeing a part of second 0 is not enough (a daemon that heard the unit from 0.5 s
        learnt that drift), nor is a link that came back after a gap (tests/test_dtemp_exact.py).
        """
        return self._dirty is None or (self._sec is not None and self._sec > self._dirty + self.WINDOW)

    def update(self, t_s: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
        """Per-sample dtemp (N,) [degC/s] for the next samples in time order."""
        return self.update_exact(t_s, temp_c)[0]

    def update_exact(self, t_s: np.ndarray, temp_c: np.ndarray,
                     seq: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per-sample dtemp (N,) [degC/s] and whether each is the unit's own (N,) bool (``exact``).

        ``seq``: the samples' seq (protocol.md: 0 at switch-on). A copy whose first sample is not
        seq 0 missed the start of its first second; a jump in seq is filled in up to ``FILL_S`` of
        unit time and leaves the seconds around it seen in part beyond. None: no gaps looked for (the
        unit's own).
        """
        t = np.asarray(t_s, dtype=np.float64)
        temp = np.asarray(temp_c, dtype=np.float64)
        real = np.ones(t.size, dtype=bool)
        gap = np.zeros(t.size, dtype=bool)
        first_seq = None if seq is None or not t.size else int(seq[0])
        if seq is not None and t.size:
            t, temp, real, gap = self._fill(np.asarray(seq, dtype=np.int64), t, temp)
        out = np.empty(t.size)
        ok = np.empty(t.size, dtype=bool)
        sec = np.floor(t).astype(np.int64)
        i = 0
        while i < t.size:
            j = i + int(np.searchsorted(sec[i:], sec[i], side="right"))
            if self._sec is not None and sec[i] != self._sec:
                self._close()
            first = self._sec is None and not (sec[i] == 0 and first_seq in (None, 0))
            if first or gap[i:j].any():  # a first sample that is not the unit's first, or a gap
                self._dirty = int(sec[i])
            self._sec = int(sec[i])
            out[i:j] = self.value
            ok[i:j] = self.exact
            self._sum += float(temp[i:j].sum())
            self._n += j - i
            i = j
        return out[real], ok[real]

    def _fill(self, seq: np.ndarray, t: np.ndarray,
              temp: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The samples with those lost in gaps of up to FILL_S put back: t [s], temp [degC], whether
        each was received, and whether a gap that is not filled came just before it.

        A gap is filled only where its seq and time agree with the sample interval seen so far (within
        a quarter of it): a jump in seq that the time does not bear out (a unit that restarted its
        count, a corrupt field) is not a run of lost samples, and filling it could need millions."""
        last = (int(seq[0]) - 1, float(t[0]), float(temp[0])) if self._last is None else self._last
        self._last = (int(seq[-1]), float(t[-1]), float(temp[-1]))
        prev_seq, prev_t = np.r_[last[0], seq[:-1]], np.r_[last[1], t[:-1]]
        prev_temp = np.r_[last[2], temp[:-1]]
        lost = (seq - prev_seq - 1) % SEQ_MODULO
        span = t - prev_t
        in_row = span[(lost == 0) & (span > 0)]
        if in_row.size:
            self._dt = float(np.median(in_row))
        where = np.flatnonzero(lost)
        fill = where[:0]
        if self._dt is not None and where.size:
            each = span[where] / (lost[where] + 1)
            on_clock = np.abs(each - self._dt) <= 0.25 * self._dt
            fill = where[on_clock & (lost[where] * self._dt <= self.FILL_S)]
        gap = np.zeros(t.size, dtype=bool)
        gap[np.setdiff1d(where, fill)] = True  # too long, or not lost samples: seen in part
        if not fill.size:
            return t, temp, np.ones(t.size, dtype=bool), gap
        n = lost[fill]
        k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n) + 1  # 1..n within each gap
        frac = k / np.repeat(n + 1, n)
        t_fill = np.repeat(prev_t[fill], n) + frac * np.repeat(span[fill], n)
        temp_fill = np.repeat(prev_temp[fill], n) + frac * np.repeat(temp[fill] - prev_temp[fill], n)
        at = np.repeat(fill, n)  # each goes in before the sample after its gap
        return (np.insert(t, at, t_fill), np.insert(temp, at, temp_fill),
                np.insert(np.ones(t.size, dtype=bool), at, False), np.insert(gap, at, False))

    def _close(self) -> None:
        if self._n and self._sec is not None:
            self._means.append((self._sec + 0.5, self._sum / self._n))
        self._sum, self._n = 0.0, 0
        if len(self._means) >= 3:
            tt, yy = np.array(self._means).T
            tt = tt - tt.mean()
            self.value = float((tt * (yy - yy.mean())).sum() / (tt * tt).sum())
