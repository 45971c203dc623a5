"""The error model the significance test and the simulation use: white + coloured + flicker + walk.

Why: a real MEMS gyro's residual is not white. A digital low-pass filter colours it at short lags,
a bias-instability (flicker) floor makes the bias wander at mid tau, and a rate random walk rises at
long tau. A test that treats the residual as white noise (or that only compares held-out blocks)
either sees effects that are not there or loses those that are.

The model, per axis, in deg/s:

    residual = white (variance ``white_var`` per sample)
             + a bank of first-order Gauss-Markov processes (correlation time T_j [s], variance v_j)
             + a random walk of intensity ``walk_q`` [(deg/s)^2 / s]

The bank's short members (T up to ``FAST_SAMPLES`` samples) are the colour (a sensor low-pass),
its longer members approximate flicker (a sum of Gauss-Markov processes with spread time constants,
the usual approximation of a 1/f spectrum). The variances are fitted to the overlapping Allan
variance of the residual by non-negative least squares on the exact discrete Allan variance of each
component, which is linear in the variances: fast, and free of the local optima of a likelihood
search. The white level is read from that fit, not from first differences, which read low when the
noise is coloured (a low-pass makes neighbouring samples alike).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

from gyrocal.sim.truth import ar2_coefficients as _ar2
from gyrocal.sim.truth import ar2_variance as _ar2_var

FAST_SAMPLES = 4.0
"""Gauss-Markov members with a correlation time up to this many samples are 'colour'."""
FAST_TAUS_SAMPLES = (0.5, 1.0, 2.0, 4.0)
SLOW_STEP = 4.0
"""Ratio between successive slow (flicker-bank) correlation times."""
TWIN_FLOOR = 0.05
"""Relative model error [fraction of the Allan variance] added in quadrature to each octave's
chi-square error in the simulation's fit (``fit_twin``). Without it the shortest octaves (thousands
of clusters, relative error 1-3 %) outweigh the last ones (relative error 30-70 %) by 20-50x, and a
model that is not exactly right at short tau is bent there at the expense of the long taus (tomisuarez
static z: 0.135 decades off at the last octave)."""
TWIN_TOP = 0.1
"""The simulation's fit uses octaves up to this fraction of the record (the fidelity range): above it
the regression (session offsets, gravity terms) has absorbed part of the residual's slow power, so the
residual's Allan deviation falls below the measured log's and would pull the model down."""
BROAD_HALF_WIDTH_HZ = 0.5
"""A line this wide or wider is broadband colour (counted in the per-sample level), not a narrow line."""


@dataclass
class NoiseModel:
    """One axis' fitted error model (see the module docstring); variances in (deg/s)^2."""

    rate_hz: float
    white_var: float
    gm: list[tuple[float, float]] = field(default_factory=list)  # (correlation time [s], variance)
    walk_q: float = 0.0  # [(deg/s)^2 / s]
    misfit: float = 0.0  # weighted squared misfit of the Allan fit (about one per octave when right)
    lines: list[tuple[float, float, float]] = field(default_factory=list)
    """Narrow-band noise (a resonance whose frequency wanders, e.g. sunsided z at 31.4 Hz): (centre
    [Hz], half width [Hz], variance [(deg/s)^2]) of a second-order (AR(2)) process; also a broad
    resonance (``resonance.find_resonance``: the 10 Hz bump of the hand-turned MPU logs). Part of the
    colour; not in the test's model (it has no power at the low frequencies the regression causes
    live at). A line at least ``BROAD_HALF_WIDTH_HZ`` wide is part of ``sample_sd`` (the broadband
    per-sample level); a narrow one is not."""

    def phi(self, tau_s: float) -> float:
        return float(np.exp(-1.0 / (self.rate_hz * tau_s)))

    @property
    def fast(self) -> list[tuple[float, float]]:
        return [(t, v) for t, v in self.gm if t * self.rate_hz <= FAST_SAMPLES and v > 0]

    @property
    def slow(self) -> list[tuple[float, float]]:
        return [(t, v) for t, v in self.gm if t * self.rate_hz > FAST_SAMPLES and v > 0]

    @property
    def sample_sd(self) -> float:
        """Per-sample SD of the high-frequency noise (white + colour + broad resonances) [deg/s]."""
        broad = sum(v for _, b, v in self.lines if b >= BROAD_HALF_WIDTH_HZ)
        return float(np.sqrt(self.white_var + sum(v for _, v in self.fast) + broad))

    @property
    def lowfreq_white_var(self) -> float:
        """White variance per sample with the colour's low-frequency power [(deg/s)^2].

        A Gauss-Markov member much faster than the effects looked for acts on them as white noise of
        variance v (1 + phi) / (1 - phi) (its spectral density at zero frequency).
        """
        out = self.white_var
        for t, v in self.fast:
            p = self.phi(t)
            out += v * (1 + p) / (1 - p)
        return float(out)

    @property
    def arw_dps_per_sqrt_hz(self) -> float:
        """Angle random walk: the white rate density at low frequency [deg/s/sqrt(Hz)]."""
        return float(np.sqrt(self.lowfreq_white_var / self.rate_hz))

    def avar(self, m: np.ndarray) -> np.ndarray:
        """Allan variance [(deg/s)^2] at cluster sizes m (samples) of the whole model."""
        m = np.asarray(m, float)
        shapes, _ = avar_shapes(m, self.rate_hz, [t for t, _ in self.gm])
        v = np.array([self.white_var, *[v for _, v in self.gm], self.walk_q])
        out = shapes @ v
        for f, b, var in self.lines:
            out = out + var * line_avar(m, f / self.rate_hz, b / self.rate_hz)
        return out

    def without_colour_and_flicker(self) -> NoiseModel:
        """The white + walk part only (what the simulation had before the noise extension)."""
        return NoiseModel(self.rate_hz, self.lowfreq_white_var, [], self.walk_q)

    def to_dict(self) -> dict:
        return {"white_dps": float(np.sqrt(self.white_var)),
                "colour": [{"tau_s": t, "sd_dps": float(np.sqrt(v))} for t, v in self.fast],
                "flicker_bank": [{"tau_s": t, "sd_dps": float(np.sqrt(v))} for t, v in self.slow],
                "walk_dps_per_sqrt_s": float(np.sqrt(self.walk_q)),
                "lines": [{"frequency_hz": f, "half_width_hz": b, "sd_dps": float(np.sqrt(v))}
                          for f, b, v in self.lines],
                "sample_sd_dps": self.sample_sd, "arw_dps_per_sqrt_hz": self.arw_dps_per_sqrt_hz}

    def simulate(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """A gap-free series (n,) of this noise [deg/s] (for the fidelity ensemble)."""
        from scipy.signal import lfilter

        x = rng.normal(0.0, np.sqrt(self.white_var), n)
        for t, v in self.gm:
            p = self.phi(t)
            e = rng.normal(0.0, np.sqrt(v * (1 - p * p)), n)
            e[0] = rng.normal(0.0, np.sqrt(v))
            x += lfilter([1.0], [1.0, -p], e)
        if self.walk_q > 0:
            x += np.cumsum(rng.normal(0.0, np.sqrt(self.walk_q / self.rate_hz), n))
        for f, b, v in self.lines:
            a1, a2 = _ar2(f / self.rate_hz, b / self.rate_hz)
            burn = int(min(20 * self.rate_hz / max(b, 1e-6), 10 * n))  # reach the stationary state
            e = rng.normal(0.0, 1.0, n + burn)
            y = lfilter([1.0], [1.0, -a1, -a2], e)[burn:]
            x += y * np.sqrt(v / _ar2_var(a1, a2))
        return x


LINE_GRID = 1 << 16
"""Frequency points on [0, 1/2] cycles/sample for a line's Allan shape (a 0.01 Hz wide line at 100 Hz
spans 13 of them)."""


def line_avar(m: np.ndarray, nu0: float, half_width: float) -> np.ndarray:
    """Allan variance per unit variance of the AR(2) line (``_ar2``) at cluster sizes m [samples].

    AVAR(m) = integral over nu in (0, 1/2) of p(nu) 2 sin^4(pi nu m) / (m^2 sin^2(pi nu)), p the
    line's normalised one-sided spectrum (the transfer function of the difference of m-sample means).
    """
    a1, a2 = _ar2(nu0, half_width)
    nu = (np.arange(LINE_GRID) + 0.5) / (2 * LINE_GRID)
    z = np.exp(-2j * np.pi * nu)
    p = 1.0 / np.abs(1 - a1 * z - a2 * z * z) ** 2
    p /= p.sum()
    m = np.asarray(m, float)
    k = 2 * np.sin(np.pi * np.outer(m, nu)) ** 4 / (m[:, None] ** 2 * np.sin(np.pi * nu)[None, :] ** 2)
    return k @ p


def octave_m(n: int, max_fraction: float = 0.25) -> np.ndarray:
    """Octave cluster sizes 1, 2, 4, ... up to ``max_fraction`` of n samples."""
    top = max(1, int(n * max_fraction))
    return 2 ** np.arange(int(np.floor(np.log2(top))) + 1)


def overlapping_avar(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Overlapping Allan variance of a rate series x (N,) at cluster sizes m [samples]."""
    cs = np.concatenate(([0.0], np.cumsum(x - np.mean(x))))
    out = np.full(len(m), np.nan)
    for i, k in enumerate(np.asarray(m, int)):
        if 2 * k >= x.size:
            continue
        ybar = (cs[k:] - cs[:-k]) / k
        d = ybar[k:] - ybar[:-k]
        out[i] = 0.5 * float(np.mean(d * d))
    return out


def _gm_avar(m: np.ndarray, phi: float) -> np.ndarray:
    """Exact Allan variance of a unit-variance discrete AR(1) with coefficient phi at cluster m."""
    if phi <= 0:
        return 1.0 / m
    q = 1.0 - phi
    pm = phi**m
    var_sum = m * (1 + phi) / q - 2 * phi * (1 - pm) / q**2
    cov_adj = phi * (1 - pm) ** 2 / q**2
    return (var_sum - cov_adj) / m**2


def avar_shapes(m: np.ndarray, rate_hz: float, gm_taus: list[float]) -> tuple[np.ndarray, list[str]]:
    """Allan variance per unit variance of each component at cluster sizes m: (len(m), 2 + G).

    Columns: white, each Gauss-Markov member (unit process variance), the walk (unit q)."""
    cols = [1.0 / m]
    names = ["white"]
    for t in gm_taus:
        cols.append(_gm_avar(m, float(np.exp(-1.0 / (rate_hz * t)))))
        names.append(f"gm{t:g}")
    cols.append((2 * m**2 + 1) / (6 * m) / rate_hz)
    names.append("walk")
    return np.column_stack(cols), names


def bank_taus(rate_hz: float, n: int) -> list[float]:
    """Correlation times [s] of the Gauss-Markov bank: fast ones, then slow ones up to n/4 samples."""
    taus = [k / rate_hz for k in FAST_TAUS_SAMPLES]
    t = 4 * FAST_SAMPLES
    while t <= n / 4:
        taus.append(t / rate_hz)
        t *= SLOW_STEP
    return taus


def fit_noise(x: np.ndarray, rate_hz: float, drop: tuple[str, ...] = (), upper: float = 0.0,
              lines: tuple[tuple[float, float], ...] = (), floor: float = 0.0,
              top: float = 0.25) -> NoiseModel:
    """Fit the error model to a residual series x (N,) [deg/s] by NNLS on its Allan variance.

    Each octave's relative error is about 1 / sqrt(N / m); the rows are weighted accordingly, so
    the short taus (many clusters) fix the white level and the colour, the long ones the walk.
    ``drop`` leaves components out ("colour", "flicker", "walk"), to measure what each is worth.
    ``upper`` > 0 fits the upper confidence limit of each octave instead (that many sigmas of the
    chi-square with the octave's degrees of freedom): the test's conservative model, because a short
    log's long-tau octaves are few and can hide a slow wander that the test would take for an effect.
    ``floor`` > 0 weights each octave by 1 / (its chi-square relative SD (+) floor) instead, and ``top``
    is the longest octave as a fraction of n (``fit_twin``: the simulation's model).
    ``lines`` ((centre, half width) [Hz], ...) adds a narrow-band member per line (``NoiseModel.lines``,
    found in the residual's spectrum by ``noisecauses.find_lines``); "colour" in ``drop`` drops them.
    """
    x = np.asarray(x, float)
    n = x.size
    m = octave_m(n, top).astype(float)
    meas = overlapping_avar(x, m)
    ok = np.isfinite(meas) & (meas > 0)
    m, meas = m[ok], meas[ok]
    if upper > 0:
        edf = _edf(n, m)
        meas = meas * edf / stats.chi2.ppf(stats.norm.sf(upper), edf)
    taus = bank_taus(rate_hz, n)
    shapes, _ = avar_shapes(m, rate_hz, taus)
    lines = () if "colour" in drop else tuple(lines)
    if lines:
        shapes = np.column_stack([shapes, *[line_avar(m, f / rate_hz, b / rate_hz) for f, b in lines]])
    keep = np.ones(shapes.shape[1], dtype=bool)
    iw = shapes.shape[1] - 1 - len(lines)  # the walk's column (the lines follow it)
    nf = len(FAST_TAUS_SAMPLES)
    if "colour" in drop:
        keep[1 : 1 + nf] = False
    if "flicker" in drop:
        keep[1 + nf : iw] = False
    if "walk" in drop:
        keep[iw] = False
    w = 1.0 / (meas * _rel_sd(n, m, floor)) if floor > 0 else np.sqrt(n / m) / meas
    v, rnorm = _nnls(shapes[:, keep], meas, w)
    full = np.zeros(shapes.shape[1])
    full[keep] = v
    gm = [(t, float(vv)) for t, vv in zip(taus, full[1:iw], strict=True) if vv > 0]
    found = [(f, b, float(v)) for (f, b), v in zip(lines, full[iw + 1:], strict=True) if v > 0]
    return NoiseModel(rate_hz, float(full[0]), gm, float(full[iw]), float(rnorm**2), found)


def _rel_sd(n: int, m: np.ndarray, floor: float) -> np.ndarray:
    """Relative SD of an overlapping Allan variance estimate at cluster sizes m (chi-square with the
    octave's degrees of freedom) with a relative model error ``floor`` in quadrature."""
    return np.sqrt(2.0 / _edf(n, m) + floor**2)


def fit_twin(x: np.ndarray, rate_hz: float, lines: tuple[tuple[float, float], ...] = ()) -> NoiseModel:
    """The simulation's error model (the twin's): ``fit_noise`` with each octave weighted by its
    chi-square error plus ``TWIN_FLOOR``, over the octaves up to ``TWIN_TOP`` of the record."""
    return fit_noise(x, rate_hz, lines=lines, floor=TWIN_FLOOR, top=TWIN_TOP)


def twin_chi2(model: NoiseModel, x: np.ndarray) -> tuple[float, int]:
    """How well a model explains a series' Allan curve: sum over the ``fit_twin`` octaves of
    ((measured - model) / (model x relative SD))^2, and the number of octaves. About chi-square with
    that many degrees of freedom when the model is right (the octaves are nearly independent)."""
    n = x.size
    m = octave_m(n, TWIN_TOP).astype(float)
    meas = overlapping_avar(np.asarray(x, float), m)
    ok = np.isfinite(meas) & (meas > 0)
    m, meas = m[ok], meas[ok]
    mod = model.avar(m)
    return float(np.sum(((meas - mod) / (mod * _rel_sd(n, m, TWIN_FLOOR))) ** 2)), int(m.size)


def _nnls(shapes: np.ndarray, meas: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Non-negative variances minimising |w (shapes v - meas)|^2 (columns scaled for conditioning)."""
    a = shapes * w[:, None]
    scale = np.maximum(np.max(np.abs(a), axis=0), 1e-300)
    v, rnorm = optimize.nnls(a / scale, w * meas)
    return v / scale, float(rnorm)


def _edf(n: int, m: np.ndarray) -> np.ndarray:
    """Equivalent degrees of freedom of an overlapping Allan variance of n samples at cluster sizes m
    (the white-noise formula, at least 1)."""
    return np.maximum(1.0, 3.0 * (n - 1) / (2.0 * m) - 2.0 * (n - 2) / n)


def component_need(x: np.ndarray, rate_hz: float,
                   lines: tuple[tuple[float, float], ...] = ()) -> dict[str, float]:
    """How much worse the Allan fit gets without each component (increase of the weighted misfit).

    About 1 per octave is noise; a component a log really has costs tens to thousands. ``lines`` as in
    ``fit_noise`` (part of the colour).
    """
    full = fit_noise(x, rate_hz, lines=lines).misfit
    return {c: fit_noise(x, rate_hz, (c,), lines=lines).misfit - full for c in ("colour", "flicker", "walk")}
