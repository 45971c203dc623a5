"""Overlapping Allan deviation with confidence intervals, and the IEEE 952 read-off of gyro noise terms.

Why here and not allantools: the daemon and the analysis need one short, vectorised function with
error bars and the three numbers every IMU user quotes (allan_variance_ros, imu_utils, Kalibr
configs); allantools is kept as the test oracle only (the ``[test]`` extra).

Definitions (NIST SP 1065, IEEE Std 952-1997 annex C), for a rate series y [deg/s] sampled at
fs [Hz], tau0 = 1/fs, tau = m tau0, angle x_i = tau0 * sum_{j<i} (y_j - mean y) (x_0 = 0, N + 1 points):

    sigma^2(tau) = sum_i (x_{i+2m} - 2 x_{i+m} + x_i)^2 / (2 tau^2 (N + 1 - 2m))      (SP 1065 eq. 11)

Noise terms read off the deviation sigma(tau) [deg/s]:

    angle random walk   N [deg/s/sqrt(Hz) = deg/sqrt(s)]: sigma = N / sqrt(tau), read at tau = 1 s
    bias instability    B [deg/s]: flat floor sigma_min = sqrt(2 ln 2 / pi) B = 0.664 B
    rate random walk    K [deg/s/sqrt(s)]: sigma = K sqrt(tau / 3), read at tau = 3 s

``read_noise_terms`` fits ARW and RRW as lines of fixed slope (-1/2, +1/2) in log-log through the
points of the curve whose local slope is close to that value (the allan_variance_ros / imu_utils
recipe): for ARW the run of such points nearest tau = 1 s, within a factor 2 of it, so a coloured
sensor's short-tau hump (a DLPF, a Gauss-Markov part) does not pull the line down (it read 37 % low
on a Gauss-Markov sensor with T = 20 ms, an outside check). A term whose slope the curve never shows
(no +1/2 rise, no floor before the curve ends) is not read: its value is NaN (null in JSON), ``seen``
is False and ``hi`` bounds it from above. The error bar of a read-off is the chi-squared interval of
its best point (overlapping taus are not independent estimates, so their edf are not summed).
``fit_noise_terms`` fits the three jointly (better where a walk rises out of a flicker floor). Multiply by
3600 for deg/h, by 60 for deg/sqrt(h) (N), by 3600 * 60 for deg/h/sqrt(h) (K).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ONE_SIGMA_CI = math.erf(1.0 / math.sqrt(2.0))
"""Probability inside +-1 sigma (0.6827): the confidence of every interval here by default."""

FLICKER_FLOOR = math.sqrt(2.0 * math.log(2.0) / math.pi)
"""Allan deviation floor of flicker rate noise per unit bias instability B (0.664, IEEE 952)."""


@dataclass(frozen=True)
class AllanCurve:
    """An overlapping Allan deviation at octave taus, with its confidence interval.

    All arrays have one entry per tau. ``alpha`` is the power-law noise type used for the degrees
    of freedom (frequency-PSD exponent: +2 white angle, 0 white rate (ARW), -1 flicker rate (bias
    instability), -2 rate random walk), identified from the data by lag-1 autocorrelation.
    """

    tau_s: np.ndarray
    adev: np.ndarray
    """Allan deviation [units of the input, e.g. deg/s]."""
    lo: np.ndarray
    hi: np.ndarray
    """Confidence interval of adev at ``ci`` (chi-squared with ``edf`` degrees of freedom)."""
    edf: np.ndarray
    alpha: np.ndarray
    m: np.ndarray
    n_terms: np.ndarray
    """Number of second differences averaged at each tau (N + 1 - 2m)."""
    ci: float = ONE_SIGMA_CI

    def as_dict(self) -> dict:
        """Plain lists for JSON."""
        return {"tau_s": self.tau_s.tolist(), "adev": self.adev.tolist(), "lo": self.lo.tolist(),
                "hi": self.hi.tolist(), "edf": self.edf.tolist(), "alpha": self.alpha.tolist()}


@dataclass(frozen=True)
class NoiseTerm:
    """A read-off value with its confidence interval and where on the curve it was read."""

    value: float
    lo: float
    hi: float
    tau_s: tuple[float, ...]
    """The taus [s] whose points the value was read from."""
    seen: bool = True
    """False: the curve does not show this term's slope; ``value`` is NaN and ``hi`` an upper bound."""

    def as_dict(self) -> dict:
        return {"value": self.value, "lo": self.lo, "hi": self.hi, "tau_s": list(self.tau_s),
                "seen": self.seen}


@dataclass(frozen=True)
class NoiseTerms:
    """IEEE 952 read-off of one axis: N (ARW), B (bias instability), K (rate random walk).

    Units for a series in deg/s: N deg/sqrt(s), B deg/s, K deg/s/sqrt(s). A term whose slope the
    curve never shows is not read (``NoiseTerm.seen``).
    """

    arw: NoiseTerm
    bias_instability: NoiseTerm
    rate_random_walk: NoiseTerm

    def as_dict(self) -> dict:
        return {"arw": self.arw.as_dict(), "bias_instability": self.bias_instability.as_dict(),
                "rate_random_walk": self.rate_random_walk.as_dict()}


def octave_m(n: int, max_m: int | None = None) -> np.ndarray:
    """Averaging factors 1, 2, 4, ... with at least two second differences (N + 1 - 2m >= 2)."""
    top = (n - 1) // 2 if max_m is None else min(max_m, (n - 1) // 2)
    if top < 1:
        return np.zeros(0, dtype=np.int64)
    return 2 ** np.arange(int(math.floor(math.log2(top))) + 1, dtype=np.int64)


def oadev(y: np.ndarray, rate_hz: float, m: np.ndarray | None = None,
          max_tau_s: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of rate samples y (N,): (tau [s], adev, n_terms) at octave m.

    Same numbers as ``allantools.oadev(y, rate, data_type="freq", taus="octave")``.
    """
    y = np.asarray(y, dtype=np.float64)
    if y.ndim != 1 or not np.isfinite(y).all():
        raise ValueError("oadev wants a 1-D series of finite samples; drop NaNs and gaps first")
    tau0 = 1.0 / float(rate_hz)
    if m is None:
        max_m = None if max_tau_s is None else int(math.floor(max_tau_s / tau0 + 1e-9))
        m = octave_m(y.size, max_m)
    m = np.asarray(m, dtype=np.int64)
    x = np.concatenate(([0.0], np.cumsum(y - y.mean()) * tau0))
    dev = np.empty(m.size)
    nt = np.empty(m.size, dtype=np.int64)
    for i, mj in enumerate(m):
        d = x[2 * mj:] - 2.0 * x[mj:-mj] + x[:-2 * mj]
        nt[i] = d.size
        dev[i] = math.sqrt(float(d @ d) / (2.0 * d.size)) / (mj * tau0)
    return m * tau0, dev, nt


def edf_simple(n_phase: int, m: int, alpha: int) -> float:
    """Equivalent degrees of freedom of the overlapping ADEV (NIST SP 1065 Table 5).

    n_phase is the number of angle points (samples + 1); alpha the frequency-PSD exponent.
    """
    n, mm = float(n_phase), float(m)
    if alpha == 2:
        return (n + 1) * (n - 2 * mm) / (2 * (n - mm))
    if alpha == 1:
        return math.exp(math.sqrt(math.log((n - 1) / (2 * mm)) * math.log((2 * mm + 1) * (n - 1) / 4)))
    if alpha == 0:
        return (3 * (n - 1) / (2 * mm) - 2 * (n - 2) / n) * 4 * mm**2 / (4 * mm**2 + 5)
    if alpha == -1:
        return 2 * (n - 2) / (2.3 * n - 4.9) if m == 1 else 5 * n**2 / (4 * mm * (n + 3 * mm))
    if alpha == -2:
        return (n - 2) / (mm * (n - 3) ** 2) * ((n - 1) ** 2 - 3 * mm * (n - 1) + 4 * mm**2)
    raise ValueError(f"alpha {alpha!r} must be one of 2, 1, 0, -1, -2")


def noise_alpha(y: np.ndarray, m: int, default: int = 0) -> int:
    """Power-law noise type at averaging m by lag-1 autocorrelation (Riley & Greenhall 2004).

    Averages y in blocks of m, removes a line, differences until the lag-1 ratio rho < 0.25 (at most
    twice): alpha = -round(2 rho) - 2 d, clipped to [-2, 2]. Fewer than 30 blocks: ``default``.
    """
    k = y.size // m
    if k < 30:
        return default
    z = y[:k * m].reshape(k, m).mean(axis=1)
    t = np.arange(k, dtype=np.float64)
    z = z - np.polyval(np.polyfit(t, z, 1), t)
    d = 0
    while True:
        zc = z - z.mean()
        den = float(zc @ zc)
        r1 = float(zc[:-1] @ zc[1:]) / den if den > 0 else 0.0
        rho = r1 / (1.0 + r1)
        if rho < 0.25 or d >= 2:
            return int(np.clip(int(-round(2 * rho) - 2 * d), -2, 2))
        z = np.diff(z)
        d += 1


def chi2_interval(dev: np.ndarray, edf: np.ndarray,
                  ci: float = ONE_SIGMA_CI) -> tuple[np.ndarray, np.ndarray]:
    """Interval of a deviation with ``edf`` degrees of freedom at confidence ci (SP 1065 eq. 45)."""
    from scipy import stats  # lazy: the simulator imports this module, fast and on a lean install (no scipy)

    p = (1.0 - ci) / 2.0
    dev, edf = np.asarray(dev, dtype=np.float64), np.asarray(edf, dtype=np.float64)
    lo = dev * np.sqrt(edf / stats.chi2.ppf(1.0 - p, edf))
    hi = dev * np.sqrt(edf / stats.chi2.ppf(p, edf))
    return lo, hi


def allan_curve(y: np.ndarray, rate_hz: float, max_tau_s: float | None = None,
                ci: float = ONE_SIGMA_CI) -> AllanCurve:
    """Overlapping ADEV of y (N,) [deg/s] at octave taus up to max_tau_s [s], with intervals at ci.

    The noise type of each tau is identified from the data; where too few blocks remain (long
    tau) the last identified type is carried on.
    """
    y = np.asarray(y, dtype=np.float64)
    tau, dev, nt = oadev(y, rate_hz, max_tau_s=max_tau_s)
    m = np.round(tau * rate_hz).astype(np.int64)
    alpha = np.empty(m.size, dtype=np.int64)
    edf = np.empty(m.size)
    last = 0
    for i, mj in enumerate(m):
        last = noise_alpha(y, int(mj), default=last)
        alpha[i] = last
        edf[i] = max(edf_simple(y.size + 1, int(mj), last), 1.0)
    lo, hi = chi2_interval(dev, edf, ci)
    return AllanCurve(tau, dev, lo, hi, edf, alpha, m, nt, ci)


SLOPE_TOL = 0.25
"""How far [log-log slope] a point's local slope may be from a term's own slope to be read with it."""
ARW_SPAN = 2.0
"""ARW is read from points within this factor of the -1/2 run's tau nearest 1 s."""
FLOOR_POINTS = 3
"""Octave points in a row whose local slope is flat (within SLOPE_TOL of 0) that show a bias
instability floor; a white-noise-and-walk bathtub is flat at one or two."""
WALK_SHARE = 0.25
"""A point past the minimum reads the walk only where the walk is at least this share of its Allan
variance (the rest is the ARW line's N^2 / tau); nearer the white noise the subtraction is noise."""
HUMP_FALL = 0.5
"""A flat stretch the curve later falls below this fraction of (by a point's 95 % upper bound) is a
hump (coloured noise), not a floor."""


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    """Index runs of consecutive True in ``mask``."""
    idx = np.flatnonzero(mask)
    return [r for r in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if r.size] if idx.size else []


def _line(curve: AllanCurve, slope: float, at_tau_s: float, pick: np.ndarray) -> NoiseTerm:
    """Value at ``at_tau_s`` of the line of fixed log-log ``slope`` through the points ``pick``: their
    log-offsets averaged with weights edf; the interval is the chi-squared one of the point with the
    most edf (the points are overlapping estimates of one line, not independent ones)."""
    lt, ld = np.log(curve.tau_s[pick]), np.log(curve.adev[pick])
    w = curve.edf[pick]
    offset = float(np.sum(w * (ld - slope * lt)) / np.sum(w))
    value = math.exp(offset + slope * math.log(at_tau_s))
    lo, hi = chi2_interval(np.array([value]), np.array([float(np.max(w))]), curve.ci)
    return NoiseTerm(value, float(lo[0]), float(hi[0]), tuple(float(t) for t in curve.tau_s[pick]))


def _local_slopes(curve: AllanCurve) -> np.ndarray:
    return np.gradient(np.log(curve.adev), np.log(curve.tau_s)) if curve.tau_s.size > 1 else np.zeros(1)


def read_noise_terms(curve: AllanCurve) -> NoiseTerms:
    """N, B, K of one axis from its Allan curve (module docstring for the definitions).

    B: the minimum / 0.664, with that point's interval, when the curve shows a floor (FLOOR_POINTS
    flat points in a row, not a hump the curve falls far below later). ARW: slope -1/2 at tau = 1 s,
    from the run of -1/2 points before the floor (or up to the minimum) nearest 1 s, within a factor
    ARW_SPAN of it; with no such point, the point whose slope is closest. RRW: slope +1/2 at
    tau = 3 s, through what the ARW line leaves (sigma^2 - N^2 / tau) at the points beyond the minimum
    whose local slope is +1/2 or which lie above it by their 95 % intervals, where that is at least
    WALK_SHARE of their variance; none, and it is not seen (``hi``: the +1/2 line through the last
    point's 97.5 % upper bound).
    """
    nan = NoiseTerm(float("nan"), float("nan"), float("nan"), ())
    if curve.tau_s.size == 0:
        return NoiseTerms(nan, nan, nan)
    n = curve.tau_s.size
    i_min = int(np.argmin(curve.adev))
    k = np.arange(n)
    local = _local_slopes(curve)
    lt = np.log(curve.tau_s)
    # the first floor: FLOOR_POINTS flat points in a row that the curve does not fall far below later
    # (a coloured sensor's short-tau hump or plateau is followed by the white noise's fall)
    lo95, hi95 = chi2_interval(curve.adev, curve.edf, 0.95)
    floors = [r for r in _runs(np.abs(local) <= SLOPE_TOL) if r.size >= FLOOR_POINTS
              and not (r[-1] + 1 < n and hi95[r[-1] + 1:].min() < HUMP_FALL * curve.adev[r].min())]
    floor = floors[0] if floors else None
    # ARW: before the floor (or up to the minimum)
    region = k < floor[0] if floor is not None else k <= i_min
    if not region.any():
        region = k == 0
    runs = _runs(region & (np.abs(local + 0.5) <= SLOPE_TOL))
    if runs:
        run = min(runs, key=lambda r: float(np.min(np.abs(lt[r]))))  # the run reaching nearest 1 s
        centre = run[int(np.argmin(np.abs(lt[run])))]
        pick = run[np.abs(lt[run] - lt[centre]) <= math.log(ARW_SPAN) + 1e-9]
    else:
        cand = np.flatnonzero(region)
        pick = cand[[int(np.argmin(np.abs(local[cand] + 0.5)))]]
    arw = _line(curve, -0.5, 1.0, pick)
    # B: the minimum / 0.664 when the curve shows a floor; else the minimum is only an upper bound
    # (white noise alone read 1.79 deg/h: an outside check)
    b = NoiseTerm(float(curve.adev[i_min] / FLICKER_FLOOR), float(curve.lo[i_min] / FLICKER_FLOOR),
                  float(curve.hi[i_min] / FLICKER_FLOOR), (float(curve.tau_s[i_min]),))
    if floor is None:
        b = NoiseTerm(float("nan"), 0.0, float(hi95[i_min] / FLICKER_FLOOR), b.tau_s, seen=False)  # 97.5 %
    # RRW: a +1/2 rise past the minimum (points of that slope, or points above the minimum by their
    # 95 % intervals), else the +1/2 line through the last point's upper bound
    rise = np.flatnonzero((k > i_min) & ((np.abs(local - 0.5) <= SLOPE_TOL) | (lo95 > hi95[i_min])))
    # the +1/2 line through what the ARW line leaves at each point (sigma^2 - N^2 / tau): a walk just
    # out of the white noise read 1.61x high (median), its interval holding the truth on 21 % (47
    # walks seen of 300 simulated axes, benchmarks/allan_coverage.py); where the walk is most of the
    # variance the two reads are the same
    white2 = arw.value**2 / curve.tau_s if math.isfinite(arw.value) else np.zeros(n)
    left2 = curve.adev**2 - white2
    rise = rise[left2[rise] > WALK_SHARE * curve.adev[rise] ** 2]
    if rise.size:
        walk = AllanCurve(curve.tau_s, np.sqrt(np.maximum(left2, 0.0)), curve.lo, curve.hi, curve.edf,
                          curve.alpha, curve.m, curve.n_terms, curve.ci)
        rrw = _line(walk, 0.5, 3.0, rise)
        best = rise[int(np.argmax(curve.edf[rise]))]  # the interval: that point's, less the white part
        scale = rrw.value / math.sqrt(left2[best])
        rrw = NoiseTerm(rrw.value, scale * math.sqrt(max(curve.lo[best] ** 2 - white2[best], 0.0)),
                        scale * math.sqrt(curve.hi[best] ** 2 - white2[best]), rrw.tau_s)
    else:
        last = n - 1
        bound = float(hi95[last] * math.sqrt(3.0 / curve.tau_s[last]))  # 97.5 % one-sided: a bound
        rrw = NoiseTerm(float("nan"), 0.0, bound, (float(curve.tau_s[last]),), seen=False)
    return NoiseTerms(arw, b, rrw)


def fit_noise_terms(curve: AllanCurve, max_tau_s: float | None = None,
                    min_tau_s: float | None = None) -> NoiseTerms:
    """N, B, K fitted jointly: sigma^2(tau) = N^2 / tau + (0.664 B)^2 + K^2 tau / 3, all >= 0.

    The slope read-off reads each term where its slope is closest, so where two terms overlap (a
    walk rising out of a flicker floor) it reads the sum; the joint fit does not. Weighted
    non-negative least squares on the Allan variance with weights edf / (2 sigma^4) (the variance
    of an Allan variance estimate is 2 sigma^4 / edf); 1-sigma intervals from the fit's covariance
    (delta method on the square root; a term at 0 gets [0, its 1-sigma]). The overlapping taus are
    treated as independent, so the intervals are optimistic, most for K: on a 4 h log of a walk
    under a flicker floor the fitted K scatters about +-50 % between axes (tests/test_model_allan).
    """
    from scipy.optimize import nnls

    sel = np.ones(curve.tau_s.size, dtype=bool) if max_tau_s is None else curve.tau_s <= max_tau_s
    if min_tau_s is not None:  # leave out a coloured sensor's short-tau hump, which the fit has no term for
        sel &= curve.tau_s >= min_tau_s
    tau, avar, edf = curve.tau_s[sel], curve.adev[sel] ** 2, curve.edf[sel]
    nan = NoiseTerm(float("nan"), float("nan"), float("nan"), ())
    if tau.size < 3:
        return NoiseTerms(nan, nan, nan)
    a = np.column_stack([1.0 / tau, np.full(tau.size, FLICKER_FLOOR**2), tau / 3.0])
    sw = np.sqrt(edf / 2.0) / avar                          # sqrt of the weights
    coef, _ = nnls(a * sw[:, None], np.ones(tau.size) * np.sqrt(edf / 2.0))
    cov = np.linalg.pinv((a * sw[:, None]).T @ (a * sw[:, None]))
    taus = tuple(float(t) for t in tau)
    terms = []
    for k in range(3):
        v, sd = float(coef[k]), float(np.sqrt(max(cov[k, k], 0.0)))
        val = math.sqrt(v)
        if v > 0:
            half = sd / (2.0 * val)                          # d sqrt(v) = dv / (2 sqrt(v))
            terms.append(NoiseTerm(val, max(val - half, 0.0), val + half, taus))
        else:
            terms.append(NoiseTerm(0.0, 0.0, math.sqrt(sd), taus))
    return NoiseTerms(*terms)


def gauss_markov_avar(tau_s: np.ndarray, sigma: float, corr_s: float) -> np.ndarray:
    """Allan variance of a first-order Gauss-Markov rate with stationary std sigma and time constant T.

    sigma^2(tau) = (2 sigma^2 T / tau) [1 - (T / (2 tau)) (3 - 4 e^(-tau/T) + e^(-2 tau/T))]
    (continuous time; El-Sheimy, Hou & Niu 2008, eq. 13 with q_c^2 = 2 sigma^2 / T). It rises as
    2 sigma^2 tau / (3 T) at small tau, peaks near tau = 1.89 T, and falls as 2 sigma^2 T / tau.
    """
    x = np.asarray(tau_s, dtype=np.float64) / corr_s
    # 1 - (3 - 4e^-x + e^-2x) / (2x), written to keep precision at small x
    bracket = 1.0 - (3.0 - 4.0 * np.exp(-x) + np.exp(-2.0 * x)) / (2.0 * x)
    small = x < 1e-3
    bracket = np.where(small, x * x / 3.0 - x**3 / 4.0, bracket)
    return 2.0 * sigma**2 / x * bracket
