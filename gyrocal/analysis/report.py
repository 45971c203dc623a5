"""``--report DIR``: a markdown summary and PNG plots a person can check at a glance.

Plots: the partial residual (the extended model's residual plus this finding's effect, as means in
bins of the covariate, so white noise averages away) against each finding's covariate, with the
fitted effect; Allan deviation of the residual before and after
the extension; measured against simulated Allan curves before and after (the simulation fidelity).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gyrocal.analysis.engine import Analysis  # noqa: E402
from gyrocal.analysis.segments import AXES  # noqa: E402


def _covariate(an: Analysis, cause: str, axis: str) -> tuple[np.ndarray, str]:
    """The covariate values (M,) to plot a cause against, and the axis label with its unit."""
    cols = an.prob.cols
    if cause == "temperature":
        return cols["temp"], "temperature [degC]"
    if cause == "temperature_rate":
        return cols["dtemp"], "temperature rate [degC/s]"
    if cause == "warmup":
        return cols["t_on"], "time since switch-on [s]"
    if cause == "periodic":
        f = next(x["params"]["frequency_hz"] for x in an.result["findings"] if x["cause"] == "periodic")
        return (cols["t"] * f) % 1.0, f"phase of the {f:g} Hz disturbance [cycles]"
    if cause == "scale_factor":
        return cols[f"ref_w{axis}"], f"reference rate ref_w{axis} [deg/s]"
    return cols["t"], "time [s]"


def _binned(x: np.ndarray, y: np.ndarray, n_bins: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Means of x and y in bins of equal sample count along x: white noise averages away."""
    order = np.argsort(x, kind="stable")
    parts = np.array_split(order, min(n_bins, max(1, x.size // 5)))
    return (np.array([x[p].mean() for p in parts if p.size]),
            np.array([y[p].mean() for p in parts if p.size]))


def _plot_finding(an: Analysis, f: dict, path: Path) -> None:
    fig, axs = plt.subplots(1, len(f["axes"]), figsize=(4.5 * len(f["axes"]), 3.6), squeeze=False)
    for ax, a in zip(axs[0], f["axes"], strict=True):
        x, label = _covariate(an, f["cause"], a)
        k = AXES.index(a)
        # partial residual: what is left once every other finding is removed, plus this effect
        effect = an.contributions[f["cause"]][:, k]
        ax.plot(*_binned(x, an.resid_ext[:, k] + effect), "o", ms=3, label="partial residual (binned means)")
        ax.plot(*_binned(x, effect), "-", color="C3", lw=1.2, label="fitted effect (binned)")
        ax.set_xlabel(label)
        ax.set_ylabel(f"w{a} residual [deg/s]")
        ax.set_title(f"{f['cause']}, axis {a}")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_allan(allan: dict, pairs: list[tuple[str, str]], title: str, path: Path) -> None:
    taus = np.asarray(allan["tau_s"])
    fig, axs = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, a in zip(axs, AXES, strict=True):
        for name, label in pairs:
            dev = np.asarray(allan[name][a], dtype=float)
            ax.loglog(taus[: dev.size], dev, marker=".", label=label)
        ax.set_xlabel("tau [s]")
        ax.set_ylabel("Allan deviation [deg/s]")
        ax.set_title(f"axis {a}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_fidelity(fid: dict, path: Path) -> None:
    """Per session (rows) and axis (columns): measured Allan deviation with its confidence interval
    against the simulated ensembles' medians and ranges, before and after the extension."""
    rows = fid["sessions"][:6]
    fig, axs = plt.subplots(len(rows), 3, figsize=(13, 3.0 * len(rows)), squeeze=False)
    for r, row in enumerate(rows):
        taus = np.asarray(row["tau_s"])
        for c, a in enumerate(AXES):
            ax = axs[r][c]
            m = np.asarray(row["measured"][a])
            ax.fill_between(taus, row["ci_low"][a], row["ci_high"][a], color="k", alpha=0.15)
            ax.loglog(taus, m, "k.-", label="measured (95 % CI)")
            for st, col in (("before", "tab:red"), ("after", "tab:blue")):
                lo, hi = row[f"band_{st}"][a]
                ax.fill_between(taus, lo, hi, color=col, alpha=0.15)
                ax.loglog(taus, row[f"simulated_{st}"][a], color=col,
                          label=f"simulated {st} ({row[st][a]:.2f} dec)")
            ax.set_title(f"session {row['session']}, axis {a}", fontsize=9)
            ax.set_xlabel("tau [s]")
            ax.set_ylabel("Allan deviation [deg/s]")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_report(directory: str | Path, an: Analysis, result: dict, log_path: str) -> Path:
    """Write report.md and the PNG plots into ``directory``; returns the markdown path."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    lines = [f"# gyrocal analyze: {Path(log_path).name}", "",
             f"Command: `gyrocal analyze {log_path} --report {directory}`", ""]
    s = result["samples"]
    lines += [f"{s['total']} samples at {s['rate_hz']:.4g} Hz in {s['sessions']} session(s); "
              f"{s['used']} used in {s['runs']} still runs"
              + (" (reference rates present: all samples used)" if s["with_reference"] else "") + ".",
              # noise_dps is the per-sample SD of the fitted error model (white + colour + lines), not
              # its white part (noise_model.white_dps, 0 where the colour takes it all: mikoff)
              "Noise: " + ", ".join(f"{a} {v:.3g}" for a, v in result["noise_dps"].items()
                                    if v is not None) + " deg/s per sample (SD of the fitted error model; "
              "its white part is noise_model.white_dps in the JSON).", ""]
    lines += ["## Findings", ""]
    if not result["findings"]:
        lines += ["Nothing significant beyond gravity-dependent drift and white noise.", ""]
    for i, f in enumerate(result["findings"]):
        lines += [f"### {i + 1}. {f['cause']} (axes {', '.join(f['axes'])})", "",
                  f"- explains {f['explained_fraction']:.1%} of the baseline held-out variance"
                  + (f", p = {f['p_value']:.2g}" if f["p_value"] is not None else " (a noise cause)"),
                  f"- params: `{f['params']}`", f"- {f['evidence']}", ""]
        if f["cause"] in an.contributions:
            png = f"finding_{i + 1}_{f['cause']}.png"
            _plot_finding(an, f, d / png)
            lines += [f"![{f['cause']}]({png})", ""]
        else:  # coloured_noise, bias_instability: no fitted effect; their evidence is the Allan curve
            lines += ["No fitted effect to plot: the evidence is the measured Allan deviation against "
                      "the simulation without and with it (the fidelity plot below).", ""]
    lines += ["## Gain", "", f"Held-out RMS after a {result['tau_s']:g} s moving average [deg/s]:", "",
              "| axis | baseline | extended | gain | baseline raw | extended raw |",
              "|---|---|---|---|---|---|"]
    for a in AXES:
        b, e = result["baseline"], result["extended"]
        lines.append(f"| {a} | {b['holdout_rms'][a]:.3g} | {e['holdout_rms'][a]:.3g} | "
                     f"{result['gain'][a]:.2f} | {b['holdout_rms_raw'][a]:.3g} | "
                     f"{e['holdout_rms_raw'][a]:.3g} |")
    fid, st = result["fidelity"], result["bias_stability_dps"]
    lines += ["", "## Allan deviation and simulation fidelity", "",
              f"Fidelity: {fid['metric']}.", "", "| axis | fidelity before | after | bias stability before "
              "[deg/s] | after |", "|---|---|---|---|---|"]
    for a in AXES:
        lines.append(f"| {a} | {fid['before'][a]:.3f} | {fid['after'][a]:.3f} | {st['before'][a]:.3g} | "
                     f"{st['after'][a]:.3g} |")
    _plot_allan(result["allan"], [("residual_before", "residual, baseline"),
                                  ("residual_after", "residual, extended")],
                "Allan deviation of the residual, before and after", d / "allan_before_after.png")
    _plot_fidelity(fid, d / "allan_measured_vs_simulated.png")
    lines += ["", "![Allan before/after](allan_before_after.png)", "",
              "![measured vs simulated](allan_measured_vs_simulated.png)", "", "## Diagnostics", ""]
    diag = result["diagnostics"]
    for a in AXES:
        w, r = diag["whiteness"][a], diag["residuals"]["runs"][a]
        peaks = ", ".join(f"{p['frequency_hz']:g} Hz (x{p['ratio']:g})" for p in diag["psd_peaks"][a])
        lines.append(f"- axis {a}: Ljung-Box Q={w['ljung_box_q']:.1f} (p={w['ljung_box_p']:.2g}), "
                     f"ACF lags 1-5 {w['acf_lag1_5']}; still-run mean spread {r['run_mean_excess']}x "
                     f"white noise; PSD peaks {peaks}")
    lines += ["", f"Extended model spec: `{result['extended'].get('spec_file', '(not written)')}`", ""]
    md = d / "report.md"
    md.write_text("\n".join(lines), encoding="utf-8")
    return md
