"""The calibration store after years of switch-ons: disk, start-up load time and memory per version.

    .venv/bin/python benchmarks/bench_store.py [--versions 1000,10000,40000] [--keep 1000] [--json]

Why: the daemon writes one version per push and pushes at every switch-on, for years, and it reads a
unit's whole history at the first HELLO after a start. For each count this writes that many
versions of one unit (records as the daemon writes them: seed 000's ten terms), then, in a fresh
process each: loads the store (``latest``), and prunes it to ``--keep`` versions
(``CalibrationStore.prune``, what the daemon does at each switch-on) and loads it again. Figures:
disk [MB], load [s], the resident memory the loaded history holds (RSS after the load over RSS
before it) [MB], and the time of the prune [s]. The files are written directly, without the
store's fsyncs, to keep the set-up short.
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gyrocal.daemon.store import CalibrationRecord  # noqa: E402
from gyrocal.model.terms import SEED000_TERMS  # noqa: E402

SERIAL = 4242

CHILD = r"""
import json, os, sys, time
sys.path.insert(0, sys.argv[1])
from gyrocal.daemon.store import CalibrationStore

def rss_mb():
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

state, keep = sys.argv[2], int(sys.argv[3])
rss0 = rss_mb()
t = time.perf_counter()
store = CalibrationStore(state)
store.latest(4242)
load_s = time.perf_counter() - t
out = {"load_s": round(load_s, 3), "rss_mb": round(rss_mb() - rss0, 1)}
if keep:
    t = time.perf_counter()
    out["pruned"] = len(store.prune(4242, keep))
    out["prune_s"] = round(time.perf_counter() - t, 3)
print(json.dumps(out))
"""


def history_record(version: int, rng: random.Random) -> dict[str, Any]:
    """A record the size of the demo daemon's (4.4 KB): full-precision floats, its stats' layout."""
    p = len(SEED000_TERMS)

    def xyz() -> dict[str, float]:
        return {a: rng.uniform(0.001, 0.03) for a in "xyz"}

    stats = {"samples": 286501, "still_samples": 108073, "trained_samples": 86562,
             "validation": {"blocks": 89, "stage": "full", "rms_current_dps": xyz(), "rms_new_dps": xyz(),
                            "noise_dps": rng.random(), "systematic_current_dps": rng.random(),
                            "systematic_new_dps": 0.0, "gain_z": 6.9, "passed": True},
             "predicted_drift_dph": {k: xyz() for k in ("left_poses", "left_sphere", "removes", "bound",
                                                         "left", "expected")},
             "warm_started_from": version - 1, "temp_range_c": None, "temp_information": None}
    rec = CalibrationRecord(
        serial=SERIAL, version=version, terms=list(SEED000_TERMS),
        coefficients_dps=[[rng.uniform(-0.1, 0.1) for _ in range(p)] for _ in range(3)],
        uncertainty_dps=[[rng.uniform(1e-5, 1e-4) for _ in range(p)] for _ in range(3)],
        identifiable={"rank": 9, "undetermined": ["1 + gx^2 + gy^2 + gz^2"]}, stats=stats,
        session={"boot_count": version, "fw": "1.0.0"},
        push={"status": "acked", "attempts": 1, "acked_crc": 1234, "readback_ok": True, "time": None,
              "utc": f"2026-01-01T00:00:00.{version:06d}Z",
              "predicted_drift_dph": stats["predicted_drift_dph"]})
    return rec.to_dict()


def write_history(udir: Path, versions: int, rng: random.Random, zero_coefficients: bool = False) -> None:
    """Versions 1..``versions`` of one unit as files in ``udir``, without the store's fsyncs (set-up
    speed); ``zero_coefficients``: sets that give a warm start no head start."""
    for v in range(1, versions + 1):
        rec = history_record(v, rng)
        if zero_coefficients:
            rec["coefficients_dps"] = [[0.0] * len(rec["terms"]) for _ in range(3)]
        (udir / f"v{v:06d}.json").write_text(json.dumps(rec))


def _child(state: Path, keep: int) -> dict[str, Any]:
    out = subprocess.run([sys.executable, "-c", CHILD, str(ROOT), str(state), str(keep)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def run(versions: int, keep: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as d:
        state = Path(d)
        udir = state / "units" / str(SERIAL)
        udir.mkdir(parents=True)
        write_history(udir, versions, random.Random(versions))
        disk = sum(f.stat().st_size for f in udir.iterdir()) / 1e6
        full = _child(state, keep)
        row: dict[str, Any] = {"versions": versions, "disk_mb": round(disk, 1), **full}
        if keep:
            after = _child(state, 0)
            row |= {"kept": len(list(udir.iterdir())), "load_after_s": after["load_s"],
                    "rss_after_mb": after["rss_mb"]}
        shutil.rmtree(udir)
        return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--versions", default="1000,10000,40000", help="version counts, comma separated")
    p.add_argument("--keep", type=int, default=1000, help="store.keep_versions for the prune (0: none)")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of lines")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    rows = []
    for n in (int(v) for v in args.versions.split(",")):
        rows.append(run(n, args.keep))
        if not args.json:
            print(json.dumps(rows[-1]), flush=True)
    if args.json:
        print(json.dumps({"rows": rows, "keep": args.keep, "wall_s": round(time.perf_counter() - t0, 1)},
                         indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
