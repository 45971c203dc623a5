"""gyrocal analyze finds what a seeded generator hid in a log, and nothing when nothing is hidden.

Each test passes only the log path to ``gyrocal analyze`` (the CLI entry point) and reads the
Contract 2 JSON. The many-seed false-alarm measurement is in benchmarks/bench_analyze.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gyrocal.analysis.hidden import generate, inject, write_hidden_log
from gyrocal.cli import main
from gyrocal.datasets.mikoff import load_mikoff
from gyrocal.logformat import write_log


def _analyze(log: Path) -> dict:
    out = log.with_suffix(".json")
    assert main(["analyze", str(log), "--json", str(out), "--quiet"]) == 0
    return json.loads(out.read_text())


@pytest.mark.parametrize(
    "seed, cause",
    [(1, "temperature"), (2, "temperature_rate"), (3, "warmup"), (4, "random_walk"),
     (5, "periodic"), (6, "scale_factor"), (0, None), (9, None)],
)
def test_hidden_effect_is_named_first_with_gain_on_affected_axes(tmp_path: Path, seed: int, cause) -> None:
    log = tmp_path / "hidden.csv"
    hidden = write_hidden_log(log, seed, causes=None if cause is None else [cause])
    r = _analyze(log)
    truth = hidden.causes[0]
    assert r["findings"], f"nothing found; hidden {truth} on {hidden.axes[truth]}"
    assert r["findings"][0]["cause"] == truth
    for a in hidden.axes[truth]:
        assert r["gain"][a] >= 1.5, (a, r["gain"])


@pytest.mark.parametrize("seed", [100, 101, 102, 103])
def test_null_log_has_no_finding(tmp_path: Path, seed: int) -> None:
    log = tmp_path / "null.csv"
    write_hidden_log(log, seed, causes=[])
    r = _analyze(log)
    assert r["findings"] == []
    assert set(r) >= {"findings", "tau_s", "baseline", "extended", "gain"}


def test_two_effects_both_found_larger_first(tmp_path: Path) -> None:
    log = tmp_path / "two.csv"
    hidden = write_hidden_log(log, 5, causes=["periodic", "warmup"], scales=[1.0, 2.0])
    r = _analyze(log)
    larger = max(hidden.size, key=hidden.size.get)
    names = [f["cause"] for f in r["findings"]]
    assert set(names[:2]) == {"periodic", "warmup"}
    assert names[0] == larger
    periodic = next(f for f in r["findings"] if f["cause"] == "periodic")
    assert abs(periodic["params"]["frequency_hz"] - hidden.effects.periodic_hz) < 0.01
    assert r["tau_s"] < 1.0  # the periodic finding shortens the averaging time


def test_generator_keeps_causes_distinguishable() -> None:
    cols, h = generate(3, causes=["warmup"])
    assert "temp" not in cols or np.ptp(cols["temp"]) == 0
    cols, h = generate(1, causes=["temperature"])
    first = cols["session"] == 0
    assert np.any(np.diff(cols["temp"][first]) < 0)  # it cycles, not only rises
    cols, _ = generate(6, causes=["scale_factor"])
    assert "ref_wx" in cols
    cols, _ = generate(4, causes=["random_walk"])
    assert "ref_wx" not in cols


@pytest.mark.parametrize(
    "cause, axes, amplitude, params",
    [("warmup", ["x"], 0.2, {"tau_s": 60.0}), ("periodic", ["y", "z"], 0.06, {"frequency_hz": 1.3})],
)
def test_effect_injected_into_real_mikoff_data_is_found(
    tmp_path: Path, cause: str, axes: list[str], amplitude: float, params: dict
) -> None:
    real = load_mikoff()
    cols = inject(real.columns, cause, amplitude, axes, **params)
    log = tmp_path / "real.csv"
    write_log(log, cols, real.metadata)
    r = _analyze(log)
    assert r["findings"] and r["findings"][0]["cause"] == cause
    assert set(axes) <= set(r["findings"][0]["axes"])
    for a in axes:
        assert r["gain"][a] >= 1.5
