"""Analyse every shipped real log; then remove the named regression effects and analyse again.

    .venv/bin/python benchmarks/real_logs.py [--json OUT.json] [--only NAME]

The second pass is the false-alarm measurement on real nulls (issue 12): once its named effects are
subtracted, a log should show no regression cause (temperature, temperature_rate, warmup, periodic,
scale_factor). The noise causes and the wander describe the sensor and may stay.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from gyrocal.analysis.engine import analyze
from gyrocal.datasets._common import data_dir
from gyrocal.datasets.imu_tk import load_imu_tk
from gyrocal.datasets.imucal import load_imucal
from gyrocal.datasets.mikoff import load_mikoff
from gyrocal.datasets.sunsided import load_sunsided
from gyrocal.datasets.tomisuarez import load_tomisuarez
from gyrocal.logformat import LogData

REGRESSION = ("temperature", "temperature_rate", "warmup", "periodic", "scale_factor")


def logs() -> dict:
    out = {
        f"mikoff_imu{i}": lambda i=i: load_mikoff(data_dir("mikoff_mpu9150") / f"imu{i}.log")
        for i in range(5)
    }
    out["imucal"] = load_imucal
    for f in ("imu_static_test", "imu_90_x_rot", "example_data_calibration", "example_data_tinit_calc"):
        out[f"tomi_{f}"] = lambda f=f: load_tomisuarez(data_dir("tomisuarez_mpu6050") / f"{f}.csv")
    out["sunsided_all"] = load_sunsided
    out["sunsided_10min"] = lambda: load_sunsided(
        data_dir("sunsided_mpu6050") / "unmoved-with-x-pointing-forward-10min"
    )
    out["imu_tk"] = load_imu_tk
    return out


def worst_tau(fid: dict) -> dict:
    """Per axis, the largest |log10(measured / simulated after)| at any tau of any session [decades]
    (the fidelity figure itself is the RMS over taus of the worst session)."""
    out = {}
    for a in "xyz":
        worst = 0.0
        for row in fid["sessions"]:
            m, s = np.array(row["measured"][a]), np.array(row["simulated_after"][a])
            ok = (m > 0) & (s > 0)
            if ok.any():
                worst = max(worst, float(np.max(np.abs(np.log10(m[ok] / s[ok])))))
        out[a] = round(worst, 3)
    return out


def summary(r: dict) -> dict:
    return {
        "findings": [
            {
                "cause": f["cause"],
                "axes": f["axes"],
                "explained_fraction": f["explained_fraction"],
                "p_value": f["p_value"],
                "params": {
                    k: v
                    for k, v in f["params"].items()
                    if k
                    in ("frequency_hz", "tau_s", "amplitude_dps", "fidelity_gain_decades", "dps_per_sqrt_s")
                },
            }
            for f in r["findings"]
        ],
        "gain": {a: round(v, 3) for a, v in r["gain"].items()},
        "noise_dps": {a: round(v, 4) for a, v in r["noise_dps"].items()},
        "noise_dps_first_differences": {a: round(v, 4) for a, v in r["noise_dps_first_differences"].items()},
        "fidelity_before": r["fidelity"]["before"],
        "fidelity_after": r["fidelity"]["after"],
        "fidelity_after_worst_tau": worst_tau(r["fidelity"]),
        "retimed": bool(r["samples"]["retimed"]),
        "tau_s": r["tau_s"],
        "psd_peaks": r["diagnostics"]["psd_peaks"],
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json")
    ap.add_argument("--only")
    args = ap.parse_args()
    out = {}
    for name, load in logs().items():
        if args.only and args.only not in name:
            continue
        log = load()
        t0 = time.perf_counter()
        an = analyze(log)
        r = an.result
        row = summary(r)
        row["seconds"] = round(time.perf_counter() - t0, 1)
        cols = {k: np.array(v, float) for k, v in log.columns.items()}
        idx = an.prob.usable.index
        for cause, c in an.contributions.items():
            if cause in REGRESSION:
                for k, a in enumerate("xyz"):
                    cols[f"w{a}"][idx] -= c[:, k]
        r2 = analyze(LogData(cols, log.metadata, log.extra_columns, log.source)).result
        row["after_removal"] = [f["cause"] for f in r2["findings"]]
        row["false_alarm"] = any(f["cause"] in REGRESSION for f in r2["findings"])
        out[name] = row
        print(
            name,
            json.dumps(
                {
                    k: row[k]
                    for k in (
                        "findings",
                        "fidelity_before",
                        "fidelity_after",
                        "fidelity_after_worst_tau",
                        "noise_dps",
                        "noise_dps_first_differences",
                        "after_removal",
                        "seconds",
                    )
                }
            ),
            flush=True,
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
