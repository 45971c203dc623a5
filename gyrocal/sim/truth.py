"""The virtual unit's truth model of gyro drift, shared by the simulator and the analysis.

Baseline (what our simulation of a unit assumes): seed 000's gravity-dependent drift (eq. 8-10),
a bias that jumps at every switch-on, and white noise. Extra effects (what real units also do, and
what the analysis must find): temperature level, temperature rate (seed 004's inputs), a warm-up
transient, a bias random walk (seed 003), a periodic disturbance and a scale-factor error.

Sensor noise beyond white (all zero by default, so the baseline stream is unchanged): coloured noise
(a first-order Gauss-Markov process, and/or the sensor's first-order low-pass filter on the white
noise, as an MPU-6050 DLPF), bias instability (flicker, a sum of Gauss-Markov processes spanning the
Allan taus of interest, so the Allan deviation shows a flat floor of 0.664 B) and quantisation (the
output rounded to an LSB). See docs/estimators.md "Noise model" for the Allan signature of each.

Units: rates deg/s, gravity g, temperature degC, time s. Seed 000 Table 1 gives deg/h; we convert.
The model renders sample chunks vectorised, carrying every noise state (walk, Gauss-Markov, flicker,
filter) from chunk to chunk so that a stream cut into chunks of any size is the same stream
(deterministic for a seed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from gyrocal.errors import ConfigError
from gyrocal.model.allan import FLICKER_FLOOR, gauss_markov_avar
from gyrocal.model.earth import earth_rate_body_dps, north_in_body
from gyrocal.model.terms import SEED000_TERMS, TermSpec
from gyrocal.sim.schedule import EarthFixed, Schedule

DPH = 1.0 / 3600.0
"""One deg/h in deg/s."""

SEED000_TABLE1_DPH = np.array([8.040, 7.352, 4.683, -5.26, 1.268, 0.693, -0.42, 0.145, -0.27, 0.029])
"""Seed 000 Table 1, d0..d9 for one gyro axis [deg/h, deg/h/g, deg/h/g^2]."""


def default_coefficients_dps() -> np.ndarray:
    """Default truth, shape (3, 10) [deg/s per term unit].

    x is seed 000 Table 1 exactly. The paper gives one axis only, so y and z reuse its magnitudes
    with the linear terms permuted and signs changed: three distinct, plausible axes.
    """
    d = SEED000_TABLE1_DPH
    x = d
    y = np.array([-5.10, d[2], -d[1], 3.90, d[5], d[4], d[6], -d[7], d[9], d[8]])
    z = np.array([3.30, -d[3], d[1] * 0.5, d[2], d[6], d[4], d[5], d[8], d[7], -d[9]])
    return np.vstack([x, y, z]) * DPH


def _vec3(value: float | tuple[float, float, float] = 0.0) -> np.ndarray:
    return np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()


@dataclass
class Effects:
    """Effects beyond the baseline model; all zero by default. Per-axis arrays are shape (3,)."""

    temp_dps_per_c: np.ndarray = field(default_factory=_vec3)
    """Bias slope on (temp - temp_ref_c) [deg/s per degC]."""
    temp2_dps_per_c2: np.ndarray = field(default_factory=_vec3)
    """Bias curvature on (temp - temp_ref_c)^2 [deg/s per degC^2]."""
    temp_ref_c: float = 25.0
    temp_rate_dps_per_cps: np.ndarray = field(default_factory=_vec3)
    """Bias on the temperature rate dT/dt [deg/s per degC/s]."""
    warmup_dps: np.ndarray = field(default_factory=_vec3)
    """Amplitude of exp(-t_on / warmup_tau_s) after each switch-on [deg/s]."""
    warmup_tau_s: float = 60.0
    random_walk_dps_per_sqrt_s: np.ndarray = field(default_factory=_vec3)
    """Bias random-walk intensity [deg/s / sqrt(s)]."""
    periodic_dps: np.ndarray = field(default_factory=_vec3)
    """Amplitude of a sinusoid at periodic_hz [deg/s]."""
    periodic_hz: float = 1.7
    scale_factor: np.ndarray = field(default_factory=_vec3)
    """Scale-factor error, dimensionless (output gains (1 + sf) on the true rate)."""
    bias_instability_dps: np.ndarray = field(default_factory=_vec3)
    """Bias instability B [deg/s] (datasheet figure; deg/h * DPH): flicker whose Allan deviation is
    flat at 0.664 B over ``flicker_band_s``. Part of the drift (it is bias wander, like the walk)."""
    flicker_band_s: tuple[float, float] = (1.0, 1000.0)
    """Taus [s] over which the flicker floor is flat; below it the floor rolls off, above it the
    flicker's slowest part looks like a constant bias."""
    gm_dps: np.ndarray = field(default_factory=_vec3)
    """Coloured noise: stationary std of a first-order Gauss-Markov rate [deg/s] (a noise, not drift)."""
    gm_tau_s: float = 0.1
    """Correlation time of the coloured noise [s]."""
    lowpass_hz: float = 0.0
    """Cut-off [Hz] of the sensor's first-order low-pass filter on the white noise (0 = none). The
    white level ``noise_dps`` is the filter's input, so the ARW (long-tau Allan) is unchanged and the
    per-sample std falls to noise_dps * sqrt(a / (2 - a)), a = 1 - exp(-2 pi fc / fs)."""
    quant_lsb_dps: np.ndarray = field(default_factory=_vec3)
    """Output quantisation step [deg/s per LSB] (0 = none), e.g. 1/131 for an MPU-6050 at 250 deg/s."""
    lines: list[tuple[int, float, float, float]] = field(default_factory=list)
    """Narrow-band noise (a resonance whose frequency wanders: sunsided z at 31.4 Hz, the 10 Hz bump of
    hand-turned MPU logs): (axis 0-2, centre [Hz], half width [Hz], stationary SD [deg/s]) of a
    second-order (AR(2)) process at the sample rate, poles r exp(+-i 2 pi f / fs), r = exp(-2 pi b /
    fs) (as ``gyrocal.analysis.noisemodel``). A noise, not drift."""

    def any(self) -> bool:
        return any(
            np.any(getattr(self, f) != 0)
            for f in ("temp_dps_per_c", "temp2_dps_per_c2", "temp_rate_dps_per_cps",
                      "warmup_dps", "random_walk_dps_per_sqrt_s", "periodic_dps", "scale_factor",
                      "bias_instability_dps", "gm_dps", "lowpass_hz", "quant_lsb_dps")
        ) or any(sd > 0 for _, _, _, sd in self.lines)


def flicker_components(band_s: tuple[float, float], per_decade: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Markov time constants T_k [s] and stationary stds w_k per unit B that sum to flicker.

    Equal variances at log-spaced T_k give a 1/f spectrum between 1/(2 pi T_max) and 1/(2 pi T_min)
    (the sum of Lorentzians 2 w^2 T / (1 + (2 pi f T)^2) over d ln T is ~ 1/f). T_k spans
    band_lo / 2 .. band_hi at ``per_decade`` per decade; w is set so that the analytic Allan
    deviation of the sum has a log-mean of 0.664 over the band (ripple about +-5 %, tests/test_noise).
    """
    lo, hi = float(band_s[0]), float(band_s[1])
    if not 0.0 < lo < hi:
        raise ValueError(f"flicker_band_s {band_s!r} must be two taus 0 < lo < hi [s]")
    t_lo, t_hi = lo / 6.0, hi * 3.0
    k = max(int(math.ceil(per_decade * math.log10(t_hi / t_lo))), 1) + 1
    corr = np.geomspace(t_lo, t_hi, k)
    taus = np.geomspace(lo, hi, 64)
    avar = sum(gauss_markov_avar(taus, 1.0, t) for t in corr)
    w = FLICKER_FLOOR / math.exp(0.5 * float(np.mean(np.log(avar))))
    return corr, np.full(k, w)


def ar2_coefficients(nu0: float, half_width: float) -> tuple[float, float]:
    """AR(2) coefficients (a1, a2) of x_n = a1 x_(n-1) + a2 x_(n-2) + e_n for a resonance at nu0
    [cycles/sample] with a Lorentzian half width [cycles/sample]: poles r exp(+-i 2 pi nu0), r =
    exp(-2 pi half_width)."""
    r = float(np.exp(-2.0 * np.pi * max(half_width, 1e-6)))
    return 2.0 * r * float(np.cos(2.0 * np.pi * nu0)), -r * r


def ar2_variance(a1: float, a2: float) -> float:
    """Stationary variance of that AR(2) with unit-variance e."""
    return float((1 - a2) / ((1 + a2) * ((1 - a2) ** 2 - a1 * a1)))


def _ar2_stationary(a1: float, a2: float, sd: float, rng: np.random.Generator) -> tuple[float, float]:
    """(x_(-1), x_(-2)) drawn from the stationary state of the AR(2) scaled to SD sd [deg/s]."""
    rho = a1 / (1.0 - a2)  # lag-1 autocorrelation
    z1, z2 = rng.normal(0.0, 1.0, 2)
    y1 = sd * z1
    y2 = sd * (rho * z1 + math.sqrt(max(1.0 - rho * rho, 0.0)) * z2)
    return float(y1), float(y2)


@dataclass
class Thermal:
    """Sensor temperature: warms from ambient after switch-on, plus an optional ambient cycle.

    temp = ambient + rise * (1 - exp(-t_on / tau)) + cycle_c * sin(2 pi t_on / cycle_period_s).
    """

    ambient_c: float = 25.0
    rise_c: float = 8.0
    tau_s: float = 120.0
    cycle_c: float = 0.0
    cycle_period_s: float = 600.0

    def at_boot(self, ambients_c: tuple[float, ...], boot_index: int) -> Thermal:
        """This thermal course for a run's switch-on ``boot_index`` (0 = the first): its ambient [degC]
        from ``ambients_c`` in order, the last repeating (``--ambient``); itself when none are given."""
        if not ambients_c:
            return self
        return replace(self, ambient_c=float(ambients_c[min(boot_index, len(ambients_c) - 1)]))

    def temp_c(self, t_on_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_on_s, dtype=np.float64)
        cyc = self.cycle_c * np.sin(2 * np.pi * t / self.cycle_period_s)
        return self.ambient_c + self.rise_c * (1.0 - np.exp(-t / self.tau_s)) + cyc

    def rate_c_per_s(self, t_on_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_on_s, dtype=np.float64)
        w = 2 * np.pi / self.cycle_period_s
        return self.rise_c / self.tau_s * np.exp(-t / self.tau_s) + self.cycle_c * w * np.cos(w * t)


@dataclass
class TruthModel:
    """Everything the virtual unit's output is made of."""

    coeffs_dps: np.ndarray = field(default_factory=default_coefficients_dps)
    """Gravity-dependent drift, shape (3, 10), seed 000 term order [deg/s per term unit]."""
    switch_on_bias_dps: float = 0.01
    """Std of the bias drawn anew at every switch-on [deg/s] (36 deg/h)."""
    noise_dps: float = 0.002
    """White gyro noise per sample [deg/s]."""
    accel_noise_g: float = 2e-4
    """White accelerometer noise per sample [g]."""
    thermal: Thermal = field(default_factory=Thermal)
    effects: Effects = field(default_factory=Effects)
    latitude_deg: float | None = None
    """Where the unit sits on the Earth [deg, north positive]: its gyros then read the Earth's rotation
    (15.041 deg/h) as true rate, as a real unit does. None: an Earth that does not turn."""
    heading_deg: float = 0.0
    """The heading of the unit's x axis at switch-on [deg east of north] (with ``latitude_deg``)."""

    def switch_on_bias(self, seed: int, boot: int) -> np.ndarray:
        """The bias jump of switch-on ``boot`` [deg/s], shape (3,): deterministic per (seed, boot)."""
        rng = np.random.default_rng([seed, boot, 0xB1A5])
        return rng.normal(0.0, self.switch_on_bias_dps, 3)

    def gravity_drift_dps(self, gravity_g: np.ndarray) -> np.ndarray:
        """Seed 000 eq. (8)-(10) per axis, shape (N, 3) [deg/s], from gravity (N, 3) [g]."""
        g = np.atleast_2d(gravity_g)
        phi = TermSpec.parse(SEED000_TERMS).design({"ax": g[:, 0], "ay": g[:, 1], "az": g[:, 2]})
        return phi @ self.coeffs_dps.T

    def systematic_drift_dps(
        self, gravity_g: np.ndarray, bias_dps: np.ndarray, t_on_s: np.ndarray,
        temp_c: np.ndarray, dtemp_c_per_s: np.ndarray, t_s: np.ndarray,
    ) -> np.ndarray:
        """All deterministic drift (no noise, no random walk, no scale factor), (N, 3) [deg/s]."""
        e = self.effects
        dt = (np.asarray(temp_c) - e.temp_ref_c)[:, None]
        out = self.gravity_drift_dps(gravity_g) + bias_dps
        out = out + dt * e.temp_dps_per_c + dt**2 * e.temp2_dps_per_c2
        out = out + np.asarray(dtemp_c_per_s)[:, None] * e.temp_rate_dps_per_cps
        out = out + np.exp(-np.asarray(t_on_s) / e.warmup_tau_s)[:, None] * e.warmup_dps
        out = out + np.sin(2 * np.pi * e.periodic_hz * np.asarray(t_s))[:, None] * e.periodic_dps
        return out


NOISE_FIELDS = ("noise_dps", "random_walk_dps_per_sqrt_s", "bias_instability_dps", "flicker_band_s", "gm_dps",
                "gm_tau_s", "lowpass_hz", "quant_lsb_dps", "line_x", "line_y", "line_z")
"""The truth fields ``gyrocal sim --noise NAME=VALUE`` may set (units in their names)."""


EFFECT_FIELDS = ("temp_dps_per_c", "temp2_dps_per_c2", "temp_rate_dps_per_cps", "warmup_dps", "warmup_tau_s",
                 "periodic_dps", "periodic_hz", "scale_factor")
"""The systematic effects ``gyrocal sim --effect NAME=VALUE`` may set (units in their names; scale_factor
is a fraction of the true rate, e.g. 0.001 for 1000 ppm)."""


def set_effects(model: TruthModel, items: list[str] | None) -> TruthModel:
    """Apply ``NAME=VALUE`` effects (VALUE one number, or x,y,z; signed amplitudes) to the model.

    E.g. ``warmup_dps=0.01,-0.008,0.012`` with ``warmup_tau_s=60``: a unit whose drift decays after
    switch-on, to run the daemon on terms that `gyrocal analyze` found. Raises ConfigError naming the
    setting and the fix.
    """
    scalars = ("warmup_tau_s", "periodic_hz")
    for item in items or []:
        name, vals = _setting("--effect", item, EFFECT_FIELDS)
        counts = (1,) if name in scalars else (1, 3)
        if len(vals) not in counts or not all(math.isfinite(v) for v in vals) \
                or (name in scalars and vals[0] <= 0):
            raise ConfigError(f"--effect {item!r}: give " + ("one finite number > 0" if name in scalars
                                                              else "1 or 3 finite numbers"))
        setattr(model.effects, name, vals[0] if name in scalars else _vec3(tuple(vals) if len(vals) == 3
                                                                           else vals[0]))
    return model


def _setting(flag: str, item: str, fields: tuple[str, ...]) -> tuple[str, list[float]]:
    """``NAME=VALUE`` of ``--noise`` / ``--effect``: the name (one of ``fields``) and its numbers."""
    name, _, text = (x.strip() for x in item.partition("="))
    if name not in fields or not text:
        raise ConfigError(f"{flag} {item!r}: write NAME=VALUE, NAME one of {', '.join(fields)}")
    try:
        return name, [float(v) for v in text.split(",")]
    except ValueError:
        raise ConfigError(f"{flag} {item!r}: VALUE must be numbers joined by commas") from None


def set_noise(model: TruthModel, items: list[str] | None) -> TruthModel:
    """Apply ``NAME=VALUE`` settings (VALUE one number, or x,y,z; flicker_band_s lo,hi) to the model.

    E.g. ``random_walk_dps_per_sqrt_s=1e-4``, ``bias_instability_dps=0.0028`` (10 deg/h),
    ``quant_lsb_dps=0.0076``, ``line_z=31.45,0.13,0.06`` (a narrow-band line on z: centre [Hz], half
    width [Hz], SD [deg/s]; repeatable, one more line each time). Raises ConfigError naming the
    setting and the fix.
    """
    scalars = ("noise_dps", "gm_tau_s", "lowpass_hz")
    for item in items or []:
        name, vals = _setting("--noise", item, NOISE_FIELDS)
        counts = ((2,) if name == "flicker_band_s" else (3,) if name.startswith("line_")
                  else (1,) if name in scalars else (1, 3))
        if len(vals) not in counts or not all(math.isfinite(v) and v >= 0 for v in vals):
            raise ConfigError(f"--noise {item!r}: give {' or '.join(map(str, counts))} finite numbers >= 0")
        if name.startswith("line_"):
            model.effects.lines = [*model.effects.lines, ("xyz".index(name[-1]), vals[0], vals[1], vals[2])]
        elif name == "noise_dps":
            model.noise_dps = vals[0]
        elif name == "flicker_band_s":
            model.effects.flicker_band_s = (vals[0], vals[1])
        else:
            setattr(model.effects, name, vals[0] if name in scalars else _vec3(tuple(vals) if len(vals) == 3
                                                                                   else vals[0]))
    lo, hi = model.effects.flicker_band_s
    if model.effects.gm_tau_s <= 0 or not 0 < lo < hi:
        raise ConfigError("--noise: gm_tau_s must be > 0 and flicker_band_s two taus 0 < lo < hi [s]")
    return model


class SessionStream:
    """One switch-on session of a unit, rendered in chunks of samples.

    ``chunk(n)`` returns the next n samples as columns of the log format plus truth columns:
    ``drift_wx..`` (the systematic drift, random walk and flicker in the output, deg/s) and ``still``.
    """

    def __init__(
        self, model: TruthModel, schedule: Schedule, rate_hz: float, seed: int, boot: int,
        t0_s: float = 0.0,
    ) -> None:
        self.model, self.schedule, self.rate_hz = model, schedule, float(rate_hz)
        self.seed, self.boot, self.t0_s = seed, boot, t0_s
        self.bias_dps = model.switch_on_bias(seed, boot)
        # one generator per noise stream, so a stream cut into chunks of any size is the same
        self._rng_gyro = np.random.default_rng([seed, boot, 1])
        self._rng_accel = np.random.default_rng([seed, boot, 2])
        self._rng_walk = np.random.default_rng([seed, boot, 3])
        self._rw_dps = np.zeros(3)
        self.index = 0
        self._noise = _NoiseState(model, rate_hz, seed, boot)
        self._earth: EarthFixed | None = None
        if model.latitude_deg is not None:
            up0 = schedule.poses_g[0]
            self._earth = EarthFixed(schedule, earth_rate_body_dps(
                up0, north_in_body(up0, model.heading_deg), model.latitude_deg))

    def chunk(self, n: int) -> dict[str, np.ndarray]:
        m = self.model
        i = np.arange(self.index, self.index + n)
        self.index += n
        t_on = i / self.rate_hz
        g, omega, still = self.schedule.state(t_on)
        if self._earth is not None:  # true rate, not drift: in ref_w, never in drift_w
            omega = omega + self._earth.at(t_on)
        temp = m.thermal.temp_c(t_on)
        dtemp = m.thermal.rate_c_per_s(t_on)
        t = self.t0_s + t_on
        drift = m.systematic_drift_dps(g, self.bias_dps, t_on, temp, dtemp, t)
        q = m.effects.random_walk_dps_per_sqrt_s
        if np.any(q != 0):
            steps = self._rng_walk.normal(0.0, 1.0, (n, 3)) * q * np.sqrt(1.0 / self.rate_hz)
            # sequential sums from the carried state: bit-identical whatever the chunking
            walk = np.cumsum(np.vstack([self._rw_dps, steps]), axis=0)[1:]
            self._rw_dps = walk[-1].copy()
            drift = drift + walk
        drift = drift + self._noise.flicker(n)
        gyro_noise = self._noise.coloured(self._rng_gyro.normal(0.0, m.noise_dps, (n, 3)))
        gyro_noise = gyro_noise + self._noise.line_noise(n)
        accel_noise = self._rng_accel.normal(0.0, m.accel_noise_g, (n, 3))
        gyro = self._noise.quantise(omega * (1.0 + m.effects.scale_factor) + drift + gyro_noise)
        accel = g + accel_noise
        cols = {"t": t, "temp": temp, "session": np.full(n, float(self.boot)), "still": still}
        for k, a in enumerate("xyz"):
            cols[f"w{a}"] = gyro[:, k]
            cols[f"a{a}"] = accel[:, k]
            cols[f"ref_w{a}"] = omega[:, k]
            cols[f"drift_w{a}"] = drift[:, k]
            cols[f"g{a}"] = g[:, k]
        return cols


class _NoiseState:
    """The carried states of the coloured, flicker and filter noise of one session (all exact
    discretisations at the sample interval, so chunking never changes the stream)."""

    def __init__(self, model: TruthModel, rate_hz: float, seed: int, boot: int) -> None:
        e, dt = model.effects, 1.0 / rate_hz
        self.lsb = np.asarray(e.quant_lsb_dps, dtype=np.float64)
        self.gm = np.asarray(e.gm_dps, dtype=np.float64)
        self.lp_a = 1.0 - math.exp(-2.0 * math.pi * e.lowpass_hz * dt) if e.lowpass_hz > 0 else 0.0
        self.bi = np.asarray(e.bias_instability_dps, dtype=np.float64)
        # x_n = phi x_(n-1) + sqrt(1 - phi^2) sigma w_n keeps the stationary std sigma exactly
        if np.any(self.gm != 0):
            self.rng_gm = np.random.default_rng([seed, boot, 4])
            self.gm_phi = math.exp(-dt / e.gm_tau_s)
            self.gm_x = self.rng_gm.normal(0.0, 1.0, 3) * self.gm
        if self.lp_a > 0:
            rng_lp = np.random.default_rng([seed, boot, 6])
            self.lp_y = rng_lp.normal(0.0, 1.0, 3) * model.noise_dps * math.sqrt(self.lp_a / (2 - self.lp_a))
        self.lines = [(int(k), *ar2_coefficients(f / rate_hz, b / rate_hz), float(sd))
                      for k, f, b, sd in e.lines if sd > 0]
        if self.lines:
            self.rng_ln = np.random.default_rng([seed, boot, 7])
            # the two last outputs of each line, drawn from the stationary state
            self.ln_y = [_ar2_stationary(a1, a2, sd, self.rng_ln) for _, a1, a2, sd in self.lines]
        if np.any(self.bi != 0):
            self.rng_fl = np.random.default_rng([seed, boot, 5])
            corr, w = flicker_components(e.flicker_band_s)
            self.fl_phi = np.exp(-dt / corr)
            self.fl_sig = w[:, None] * self.bi[None, :]               # (K, 3) stationary stds [deg/s]
            self.fl_x = self.rng_fl.normal(0.0, 1.0, self.fl_sig.shape) * self.fl_sig

    def flicker(self, n: int) -> np.ndarray | float:
        """The bias-instability part of the drift for the next n samples, (n, 3) [deg/s]."""
        if not np.any(self.bi != 0):
            return 0.0
        from scipy.signal import lfilter  # lazy: the default (noise-free) unit runs on a lean install

        w = self.rng_fl.normal(0.0, 1.0, (n, *self.fl_sig.shape))
        out = np.zeros((n, 3))
        for k, phi in enumerate(self.fl_phi):
            drive = w[:, k, :] * (math.sqrt(1.0 - phi * phi) * self.fl_sig[k])
            x = lfilter([1.0], [1.0, -phi], drive, axis=0, zi=(phi * self.fl_x[k])[None, :])[0]
            self.fl_x[k] = x[-1]
            out += x
        return out

    def coloured(self, white: np.ndarray) -> np.ndarray:
        """White noise (n, 3) [deg/s] through the sensor filter, plus the Gauss-Markov noise."""
        out = white
        if self.lp_a <= 0 and not np.any(self.gm != 0):
            return out
        from scipy.signal import lfilter  # lazy: the default (noise-free) unit runs on a lean install

        if self.lp_a > 0:
            a = self.lp_a
            out = lfilter([a], [1.0, a - 1.0], white, axis=0, zi=((1 - a) * self.lp_y)[None, :])[0]
            self.lp_y = out[-1].copy()
        if np.any(self.gm != 0):
            phi = self.gm_phi
            drive = self.rng_gm.normal(0.0, 1.0, white.shape) * (math.sqrt(1.0 - phi * phi) * self.gm)
            x = lfilter([1.0], [1.0, -phi], drive, axis=0, zi=(phi * self.gm_x)[None, :])[0]
            self.gm_x = x[-1].copy()
            out = out + x
        return out

    def line_noise(self, n: int) -> np.ndarray | float:
        """The narrow-band lines for the next n samples, (n, 3) [deg/s] (states carried)."""
        if not self.lines:
            return 0.0
        from scipy.signal import lfilter, lfiltic  # lazy: the default unit runs on a lean install

        out = np.zeros((n, 3))
        w = self.rng_ln.normal(0.0, 1.0, (n, len(self.lines)))
        for j, (k, a1, a2, sd) in enumerate(self.lines):
            den = [1.0, -a1, -a2]
            drive = w[:, j] * (sd / math.sqrt(ar2_variance(a1, a2)))
            y1, y2 = self.ln_y[j]
            y = lfilter([1.0], den, drive, zi=lfiltic([1.0], den, [y1, y2]))[0]
            if n >= 2:
                self.ln_y[j] = (float(y[-1]), float(y[-2]))
            elif n == 1:
                self.ln_y[j] = (float(y[-1]), y1)
            out[:, k] += y
        return out

    def quantise(self, gyro: np.ndarray) -> np.ndarray:
        """The output rounded to its LSB on the axes that have one."""
        if not np.any(self.lsb > 0):
            return gyro
        lsb = np.where(self.lsb > 0, self.lsb, 1.0)
        return np.where(self.lsb > 0, np.round(gyro / lsb) * lsb, gyro)


def pose_drift_rms_dps(
    model: TruthModel, schedule: Schedule, bias_dps: np.ndarray,
    compensation_dps: np.ndarray | None = None,
) -> np.ndarray:
    """RMS over the schedule's poses of the drift left in the output, (3,) [deg/s] (Contract 4).

    ``compensation_dps`` (K, 3) is what the applied coefficient set subtracts at each pose. Extra
    effects are evaluated at switch-on ambient conditions; noise is excluded by definition.
    """
    k = len(schedule.poses_g)
    zeros = np.zeros(k)
    drift = model.systematic_drift_dps(
        schedule.poses_g, bias_dps, np.full(k, np.inf), np.full(k, model.thermal.ambient_c),
        zeros, zeros,
    )
    if compensation_dps is not None:
        drift = drift - compensation_dps
    return np.sqrt(np.mean(drift**2, axis=0))
