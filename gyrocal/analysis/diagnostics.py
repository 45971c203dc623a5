"""What the simulation gets wrong, as numbers: whiteness, spectrum, Allan deviation, covariates.

Allan deviations are computed on the used samples of the log concatenated in time order (gaps from
moves and switch-ons are closed up); they compare like with like because the measured and the
simulated series share those gaps. The fidelity distance between two Allan curves is the RMS of
log10(measured / simulated) over the octave taus, in decades: 0 is a perfect match, 0.3 is a factor
of two.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy import stats

from gyrocal.analysis.baseline import Problem
from gyrocal.analysis.candidates import F_MIN_HZ, gridded, spectrum
from gyrocal.analysis.segments import AXES
from gyrocal.model.allan import oadev


def autocorrelation(r: np.ndarray, max_lag: int) -> np.ndarray:
    """Sample autocorrelation of r (N,) at lags 1..max_lag (FFT based)."""
    x = r - np.mean(r)
    n = x.size
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(x, nfft)
    acov = np.fft.irfft(f * np.conj(f), nfft)[: max_lag + 1]
    return acov[1:] / acov[0] if acov[0] > 0 else np.zeros(max_lag)


def ljung_box(r: np.ndarray, lags: int = 20) -> tuple[float, float]:
    """Ljung-Box Q statistic over ``lags`` lags and its p-value (white residual: p uniform)."""
    n = r.size
    rho = autocorrelation(r, lags)
    q = float(n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, lags + 1))))
    return q, float(stats.chi2.sf(q, lags))


def whiteness(r: np.ndarray, lags: int = 20) -> dict:
    """Per-axis residual autocorrelation (first lags) and the Ljung-Box test, r (N, 3)."""
    out = {}
    for k, a in enumerate(AXES):
        q, p = ljung_box(r[:, k], lags)
        out[a] = {"acf_lag1_5": np.round(autocorrelation(r[:, k], 5), 4).tolist(),
                  "ljung_box_q": round(q, 2), "ljung_box_p": p, "lags": lags}
    return out


def psd_peaks(prob: Problem, r: np.ndarray, n_peaks: int = 3) -> dict:
    """The largest spectral peaks (>= F_MIN_HZ) of the residual per axis, gap-aware (zero filled).

    ``ratio`` is the peak power over the median power of the band: about 10 or less is what white
    noise gives for the largest of thousands of bins.
    """
    grids = gridded(prob, r, np.ones(prob.n, dtype=bool))
    f, p = spectrum(prob, grids)
    band = (f >= F_MIN_HZ) & (f <= 0.45 * prob.rate_hz)
    out = {}
    for k, a in enumerate(AXES):
        pb, fb = p[band, k], f[band]
        if pb.size == 0:
            out[a] = []
            continue
        med = float(np.median(pb)) or 1e-300
        peaks: list[dict] = []
        for j in np.argsort(pb)[::-1]:
            if all(abs(fb[j] - q["frequency_hz"]) > 3 * (f[1] - f[0]) for q in peaks):
                peaks.append({"frequency_hz": round(float(fb[j]), 4), "ratio": round(float(pb[j] / med), 1)})
            if len(peaks) == n_peaks:
                break
        out[a] = peaks
    return out


def covariate_table(prob: Problem, r: np.ndarray, extra: list[str]) -> dict:
    """Correlation and slope of the residual's run means against each candidate covariate.

    Run means (one value per still run) average the white noise away so a slow dependence shows.
    """
    names = [c for c in ("temp", "dtemp", "t_on", "ref_wx", "ref_wy", "ref_wz", *extra) if c in prob.cols]
    run = prob.usable.run
    cnt = np.maximum(np.bincount(run), 1)
    out: dict = {}
    for c in names:
        x = np.bincount(run, weights=prob.cols[c]) / cnt
        if np.std(x) == 0:
            continue
        row = {}
        for k, a in enumerate(AXES):
            yv = np.bincount(run, weights=r[:, k]) / cnt
            rho = float(np.corrcoef(x, yv)[0, 1]) if np.std(yv) > 0 else 0.0
            slope = float(np.cov(x, yv)[0, 1] / np.var(x, ddof=1))
            row[a] = {"corr": round(rho, 4), "slope_dps_per_unit": slope}
        out[c] = row
    return out


def adev(x: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation at octave taus [s] of a rate series x [deg/s]."""
    taus, dev, _ = oadev(np.asarray(x, float), rate_hz)
    return taus, dev


def fidelity(measured: np.ndarray, simulated: np.ndarray) -> float:
    """RMS of log10(measured / simulated Allan deviation) [decades] over common taus."""
    n = min(measured.size, simulated.size)
    ok = (measured[:n] > 0) & (simulated[:n] > 0)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(np.mean(np.log10(measured[:n][ok] / simulated[:n][ok]) ** 2)))


def allan_block(prob: Problem, series: Mapping[str, np.ndarray]) -> dict:
    """Allan deviation curves per axis for named (M, 3) series: {"tau_s": [...], name: {x: [...]}}."""
    out: dict = {}
    for name, x in series.items():
        out[name] = {}
        for k, a in enumerate(AXES):
            taus, dev = adev(x[:, k], prob.rate_hz)
            out["tau_s"] = np.round(taus, 5).tolist()
            out[name][a] = dev.tolist()
    return out
