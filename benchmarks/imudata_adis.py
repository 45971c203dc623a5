"""`gyrocal analyze` on the six ADIS16405 static recordings of SMAC-Group/imudata (issue 12).

    pip install rdata          # reads R .rda files; not a gyrocal dependency
    python benchmarks/imudata_adis.py /path/to/imudata [--work DIR] [--only 1,2] [--json]

Why: issue 12's independent check used one of these recordings (2.8 h at 100 Hz, still): the
old analysis named a walk 6-10x the Allan rate, left a flicker floor unnamed, and its simulation
missed by 0.41-0.53 decade. The data are for measurement only: the package's licence does not let
us ship them, so this script converts them from a clone of https://github.com/SMAC-Group/imudata
(data/adis_16405_imuN.rda).

What the files hold (checked in the data, as the package documents only "ADIS 16405 IMU at 100
Hz"): an R ``imu`` matrix of 1,000,000 rows x 6 columns, "Gyro. X/Y/Z" then "Accel. X/Y/Z", with a
``freq`` attribute. The gyro columns step by exactly 0.05, the ADIS16405's gyro LSB in deg/s
(+-300 deg/s range), so they are deg/s, quantised; the accelerometer steps by 0.00333 (3.33 mg,
its LSB) with z near -1.017, so they are g. There are no time stamps: t = i / 100 s. There is no
temperature column.

Per recording it writes DIR/adisN.csv (gyrocal's log format), runs ``gyrocal analyze`` with
``--json`` and ``--report`` and prints the findings, the fidelity before / after (RMS over taus of
the worst session, decades), the worst single tau, the joint-fit bias instability B [deg/h] and
the analysis' wall time.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from real_logs import worst_tau  # noqa: E402

RATE_HZ = 100.0
GYRO_LSB_DPS = 0.05


def convert(rda: Path, out: Path) -> int:
    """One .rda recording -> gyrocal CSV (t [s], w [deg/s], a [g]); returns the row count."""
    try:
        import rdata
    except ImportError:
        raise SystemExit("this benchmark reads R .rda files with the `rdata` package: "
                         "pip install rdata") from None
    import warnings

    with warnings.catch_warnings():  # "Missing constructor for R class imu": the matrix is what we want
        warnings.simplefilter("ignore")
        obj = rdata.conversion.convert(rdata.parser.parse_file(rda))
    a = np.asarray(next(iter(obj.values())), dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 6:
        raise SystemExit(f"{rda}: expected 6 columns (gyro x y z, accel x y z), got {a.shape}")
    steps = np.diff(np.unique(a[:, 0]))
    if not np.allclose(steps.min(), GYRO_LSB_DPS, rtol=1e-3):
        raise SystemExit(f"{rda}: gyro x steps by {steps.min():g}, not the ADIS16405's "
                         f"{GYRO_LSB_DPS} deg/s LSB")
    t = np.arange(a.shape[0]) / RATE_HZ
    np.savetxt(out, np.column_stack([t, a]), delimiter=",", fmt=["%.2f"] + ["%.5f"] * 6,
               header="t,wx,wy,wz,ax,ay,az", comments="")
    return a.shape[0]


def summary(r: dict, seconds: float) -> dict:
    terms = r["allan_terms"]
    return {
        "findings": {f["cause"]: f["axes"] for f in r["findings"]},
        "fidelity_before": r["fidelity"]["before"], "fidelity_after": r["fidelity"]["after"],
        "worst_single_tau_after": worst_tau(r["fidelity"]),
        "bias_instability_dph": {a: round(terms[a]["joint_fit"]["bias_instability"]["value"] * 3600, 1)
                                 for a in "xyz"},
        "arw_deg_per_sqrt_h": {a: round(terms[a]["arw"]["value"] * 60, 3) for a in "xyz"},
        "seconds": round(seconds, 1),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("imudata", help="a clone of SMAC-Group/imudata")
    ap.add_argument("--work", default="out/imudata_adis", help="where the CSVs, JSONs and reports go")
    ap.add_argument("--only", default="1,2,3,4,5,6", help="recordings to run (1-6)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    out = {}
    for i in [int(x) for x in args.only.split(",") if x]:
        csv, js = work / f"adis{i}.csv", work / f"adis{i}.json"
        if not csv.exists():
            convert(Path(args.imudata) / "data" / f"adis_16405_imu{i}.rda", csv)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "gyrocal.cli", "analyze", str(csv), "--json", str(js),
                        "--report", str(work / f"rep{i}"), "--quiet"], check=True)
        out[f"adis{i}"] = summary(json.loads(js.read_text()), time.perf_counter() - t0)
        if not args.json:
            print(f"adis{i}", json.dumps(out[f"adis{i}"]), flush=True)
    if args.json:
        print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
