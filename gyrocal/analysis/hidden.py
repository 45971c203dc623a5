"""A seeded generator of logs that hide one or more drift effects, for tests and benchmarks.

The seed chooses the cause (unless given), the affected axes and the size, at sizes a careful
engineer could detect against the noise. It keeps causes distinguishable, as issue 5 asks:
temperature cycles (it does not only rise with time) when the cause is temperature or its rate;
the temperature is flat or absent when the cause is warm-up; reference rates are written only when
the cause is a scale factor. ``inject`` adds an effect to a real log instead, so real noise is used.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gyrocal.logformat import write_log
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import Effects, SessionStream, Thermal, TruthModel

CAUSES = ("temperature", "temperature_rate", "warmup", "random_walk", "periodic", "scale_factor")
AXES = ("x", "y", "z")


@dataclass
class Hidden:
    """What a generated log hides: causes, affected axes, and the truth effects used."""

    causes: list[str]
    axes: dict[str, list[str]] = field(default_factory=dict)
    effects: Effects = field(default_factory=Effects)
    thermal: Thermal = field(default_factory=Thermal)
    size: dict[str, float] = field(default_factory=dict)  # a scalar size per cause (for ranking)


def _axes(rng: np.random.Generator) -> np.ndarray:
    mask = np.zeros(3)
    mask[rng.choice(3, size=int(rng.integers(1, 4)), replace=False)] = 1.0
    return mask


def _signs(rng: np.random.Generator) -> np.ndarray:
    return rng.choice([-1.0, 1.0], 3)


def _add(h: Hidden, cause: str, rng: np.random.Generator, session_s: float, scale: float) -> None:
    """Put one cause into h.effects / h.thermal; ``scale`` multiplies the drawn size."""
    e, m = h.effects, _axes(rng)
    u = rng.uniform(1.0, 2.0) * scale
    if cause in ("temperature", "temperature_rate"):
        h.thermal = Thermal(rise_c=rng.uniform(0.0, 1.0), tau_s=120.0, cycle_c=rng.uniform(3.0, 6.0),
                            cycle_period_s=session_s / rng.integers(1, 3))
    if cause == "temperature":
        e.temp_dps_per_c = m * _signs(rng) * 1.5e-3 * u
        size = 1.5e-3 * u * h.thermal.cycle_c / np.sqrt(2)
    elif cause == "temperature_rate":
        w = 2 * np.pi / h.thermal.cycle_period_s
        e.temp_rate_dps_per_cps = m * _signs(rng) * 5e-3 * u / (h.thermal.cycle_c * w)
        size = 5e-3 * u / np.sqrt(2)
    elif cause == "warmup":
        e.warmup_dps = m * _signs(rng) * 0.02 * u
        e.warmup_tau_s = float(rng.uniform(20.0, 50.0))
        size = 0.02 * u * np.sqrt(e.warmup_tau_s / (2 * session_s))
    elif cause == "random_walk":
        e.random_walk_dps_per_sqrt_s = m * 1e-3 * u
        size = 1e-3 * u * np.sqrt(session_s / 6)
    elif cause == "periodic":
        e.periodic_dps = m * 5e-3 * u
        e.periodic_hz = float(round(rng.uniform(0.3, 3.0), 3))
        size = 5e-3 * u / np.sqrt(2)
    else:  # scale_factor
        m = np.ones(3)
        e.scale_factor = m * _signs(rng) * 1e-3 * u
        size = 1e-3 * u * 60.0
    h.axes[cause] = [a for a, k in zip(AXES, m, strict=True) if k]
    h.size[cause] = float(size)


def generate(
    seed: int, causes: Sequence[str] | None = None, n_sessions: int = 3, session_s: float = 180.0,
    rate_hz: float = 25.0, scales: Sequence[float] | None = None,
) -> tuple[dict[str, np.ndarray], Hidden]:
    """Log columns with the hidden causes (``[]`` for the null case) and what was hidden.

    ``causes=None`` lets the seed choose one cause. The schedule is the 18-pose tumble.
    """
    rng = np.random.default_rng([seed, 0x41DE])
    chosen = [CAUSES[int(rng.integers(len(CAUSES)))]] if causes is None else list(causes)
    h = Hidden(chosen)
    h.thermal = Thermal(rise_c=rng.uniform(0.0, 4.0), tau_s=120.0)
    for i, c in enumerate(chosen):
        _add(h, c, rng, session_s, (scales[i] if scales else 1.0))
    if "warmup" in chosen:
        h.thermal = Thermal(rise_c=0.0, cycle_c=0.0)
    model = TruthModel(thermal=h.thermal, effects=h.effects)
    n = int(session_s * rate_hz)
    parts = [SessionStream(model, tumble(), rate_hz, seed, boot, t0_s=boot * (session_s + 60.0)).chunk(n)
             for boot in range(n_sessions)]
    cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    keep = ["t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session"]
    if "scale_factor" in chosen:
        keep += ["ref_wx", "ref_wy", "ref_wz"]
    if "warmup" in chosen and rng.random() < 0.5:
        keep.remove("temp")
    return {k: cols[k] for k in keep}, h


BACKGROUNDS = ("white", "coloured", "flicker", "quantised", "real_like")


def add_background(cols: dict[str, np.ndarray], kind: str, seed: int, level_dps: float = 0.002
                   ) -> dict[str, np.ndarray]:
    """Add a non-white noise background to the gyro columns (a null for the false-alarm rate).

    coloured: a first-order low-pass (Gauss-Markov, 2-sample correlation time) of the white noise
    level, as a sensor DLPF makes it; flicker: a bank of Gauss-Markov processes at 3, 30 and 300 s
    (a bias-instability floor of about the white level at 1 s); quantised: the output rounded to
    a step of 1.5 x the white level (a 16-bit MEMS at its finest range); real_like: all three.
    """
    from gyrocal.analysis.noisemodel import NoiseModel

    out = dict(cols)
    t, session = cols["t"], cols["session"]
    rate = 1.0 / float(np.median(np.diff(t)))
    rng = np.random.default_rng([seed, 0xBA6])
    gm: list[tuple[float, float]] = []
    if kind in ("coloured", "real_like"):
        gm.append((2.0 / rate, (1.5 * level_dps) ** 2))
    if kind in ("flicker", "real_like"):
        gm += [(3.0, (0.4 * level_dps) ** 2), (30.0, (0.4 * level_dps) ** 2), (300.0, (0.4 * level_dps) ** 2)]
    model = NoiseModel(rate, 0.0, gm, 0.0)
    for a in AXES:
        w = out[f"w{a}"].copy()
        if gm:
            for s in np.unique(session):
                m = session == s
                w[m] += model.simulate(int(m.sum()), rng)
        if kind in ("quantised", "real_like"):
            step = 1.5 * level_dps
            w = np.round(w / step) * step
        out[f"w{a}"] = w
    return out


def write_hidden_log(path: str | Path, seed: int, **kwargs) -> Hidden:
    """Generate with ``generate`` and write a Contract 1 log; returns what was hidden."""
    cols, h = generate(seed, **kwargs)
    write_log(path, cols, {"generator": "gyrocal.analysis.hidden", "seed": str(seed)})
    return h


def inject(columns: Mapping[str, np.ndarray], cause: str, amplitude_dps: float, axes: Sequence[str],
           seed: int = 0, **params: float) -> dict[str, np.ndarray]:
    """A copy of a real log's columns with one effect added to the gyro of ``axes``.

    warmup: amplitude * exp(-t_on / tau_s); periodic: amplitude * sin(2 pi frequency_hz t);
    random_walk: a walk of intensity amplitude [deg/s/sqrt(s)]. Time since switch-on is per session.
    """
    out = {k: np.array(v, dtype=float) for k, v in columns.items()}
    t = out["t"]
    session = out.get("session", np.zeros_like(t))
    uniq, first = np.unique(session, return_index=True)
    t_on = t - t[first][np.searchsorted(uniq, session)]
    if cause == "warmup":
        sig = amplitude_dps * np.exp(-t_on / params.get("tau_s", 30.0))
    elif cause == "periodic":
        sig = amplitude_dps * np.sin(2 * np.pi * params.get("frequency_hz", 1.0) * t)
    elif cause == "random_walk":
        rng = np.random.default_rng([seed, 0x3A1C])
        dt = np.diff(t, prepend=t[0])
        sig = np.cumsum(rng.normal(0, 1, t.size) * amplitude_dps * np.sqrt(np.maximum(dt, 0)))
    else:
        raise ValueError(f"inject: cause {cause!r} is not supported; use warmup, periodic or random_walk")
    for a in axes:
        out[f"w{a}"] = out[f"w{a}"] + sig
    return out


@dataclass
class HardCase:
    """One log of the harder hidden set: causes, size in units of the per-sample noise, background."""

    seed: int
    causes: list[str]
    size_sigma: float
    background: str = "white"


HARD_SET: tuple[HardCase, ...] = (
    *(HardCase(300 + i, [c], s) for i, (c, s) in enumerate(zip(
        ("temperature", "temperature_rate", "warmup", "periodic", "random_walk", "scale_factor"),
        (0.1, 0.2, 0.3, 0.1, 0.2, 0.3), strict=True))),
    HardCase(310, ["temperature", "temperature_rate"], 0.3),
    HardCase(311, ["periodic", "warmup"], 0.2),
    HardCase(312, ["warmup"], 0.3, "flicker"),
    HardCase(313, ["periodic"], 0.2, "real_like"),
    HardCase(314, ["temperature"], 0.3, "quantised"),
    HardCase(320, [], 0.0, "coloured"),
    HardCase(321, [], 0.0, "quantised"),
    HardCase(322, [], 0.0, "flicker"),
    HardCase(323, [], 0.0, "real_like"),
)
"""Effects at 0.1-0.3 sigma, confounded pairs, non-white backgrounds and nulls, on long sessions
(2 x 600 s at 25 Hz); sigma = the truth model's white noise per sample (0.002 deg/s)."""


def generate_hard(case: HardCase, session_s: float = 600.0, n_sessions: int = 2
                  ) -> tuple[dict[str, np.ndarray], Hidden]:
    """The columns of one hard case: each effect rescaled so its size (``Hidden.size``) is
    ``size_sigma`` x the white noise per sample, then the background added."""
    sigma = TruthModel().noise_dps
    scales = None
    if case.causes:
        _, h = generate(case.seed, case.causes, n_sessions=n_sessions, session_s=session_s)
        scales = [case.size_sigma * sigma / h.size[c] for c in case.causes]
    cols, h = generate(case.seed, case.causes, n_sessions=n_sessions, session_s=session_s, scales=scales)
    if case.background != "white":
        cols = add_background(cols, case.background, case.seed, sigma)
    return cols, h
