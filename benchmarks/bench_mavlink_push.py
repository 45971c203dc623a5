"""Benchmark: how long a MAVLink parameter push takes, with and without the boot gate.

    .venv/bin/python benchmarks/bench_mavlink_push.py [--pushes 5] [--drops 0,3] [--no-gate] [--json OUT]

Each parameter request of a push waits for an IMU sample newer than the autopilot's last answer
(gyrocal/mavlink/link.py ``_clock_seen``), so that a reboot mid-push is seen before the rest of the
set reaches the new boot. This measures what that costs: for each autopilot (the virtual PX4 and
ArduPilot of ``gyrocal sim --link mavlink``, 250 Hz, over a pty) and each number of lost PARAM_VALUE
echoes (``--drops``, the simulator's ``--drop-param-values``, per push), ``--pushes`` pushes of the
same cubic, timed from the COEFF_WRITE to its ACK [s], with the gate and with it replaced by "always
open" (``--no-gate`` runs only that). Figures: median and max per case, and the ratio gated / open
of the medians, measured in the same run (these machines are noisy).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from gyrocal.daemon.ring import RingBuffer  # noqa: E402
from gyrocal.mavlink.link import MavlinkLink  # noqa: E402
from gyrocal.protocol.messages import CoeffAck, CoeffNak, CoeffWrite, Hello  # noqa: E402
from gyrocal.protocol.termsets import TEMP_POLY3_ID  # noqa: E402
from tests.sim_helpers import SimProcess, wait_for  # noqa: E402

Q = np.array([[0.05, 1e-3, -2e-5, 3e-7], [-0.02, -5e-4, 1e-5, 0.0], [0.01, 2e-4, 0.0, -1e-7]])


def one_case(kind: str, drops: int, pushes: int, gate: bool) -> dict[str, Any]:
    """Times [s] of ``pushes`` pushes; with lost echoes, each against a fresh virtual autopilot that
    drops the first ``drops`` echoes (the simulator counts its drops down once)."""
    if not drops:
        return _pushes(kind, 0, pushes, gate)
    runs = [_pushes(kind, drops, 1, gate) for _ in range(pushes)]
    times = [t for r in runs for t in r.get("times_s", [])]
    if not times:
        return {"error": "no push timed"}
    return {"median_s": round(statistics.median(times), 3), "max_s": round(max(times), 3),
            "times_s": times, "naks": sum(r.get("naks", 0) for r in runs)}


def _pushes(kind: str, drops: int, pushes: int, gate: bool) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        extra = ["--drop-param-values", str(drops)] if drops else []
        with SimProcess("--link", "mavlink", "--autopilot", kind, "--rate", "250", "--warmup-tau", "30",
                        *extra, tmp_path=tmp) as ap:
            got: list[Any] = []
            link = MavlinkLink(ap.address, RingBuffer(1 << 16), got.append, None, autopilot=kind,
                               state_file=str(tmp / "mav.json"))
            if not gate:
                link._clock_seen = lambda now: True  # type: ignore[method-assign]
            link.start()
            try:
                if not wait_for(lambda: any(isinstance(m, Hello) for m in got), 20):
                    return {"error": "no HELLO"}
                wait_for(lambda: link.stats()["samples"] > 300, 10)
                times, naks = [], 0
                for k in range(pushes):
                    n0 = len(got)
                    t0 = time.monotonic()
                    link.send(CoeffWrite(10 + k, TEMP_POLY3_ID, Q * (1 + 0.01 * k)))
                    wait_for(lambda n0=n0: any(isinstance(m, CoeffAck | CoeffNak) for m in got[n0:]),
                             60, 0.001)
                    times.append(time.monotonic() - t0)
                    naks += any(isinstance(m, CoeffNak) for m in got[n0:])
                    time.sleep(0.3)
            finally:
                link.stop()
    return {"median_s": round(statistics.median(times), 3), "max_s": round(max(times), 3),
            "times_s": [round(t, 3) for t in times], "naks": naks}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pushes", type=int, default=5)
    p.add_argument("--drops", default="0,3", help="lost echoes per push, comma-separated (default 0,3)")
    p.add_argument("--no-gate", action="store_true", help="only the gate replaced by 'always open'")
    p.add_argument("--json", metavar="OUT")
    args = p.parse_args(argv)
    rows = []
    for kind in ("px4", "ardupilot"):
        for drops in (int(x) for x in args.drops.split(",")):
            row: dict[str, Any] = {"autopilot": kind, "drops": drops}
            for gate in ([False] if args.no_gate else [True, False]):
                row["gate" if gate else "open"] = one_case(kind, drops, args.pushes, gate)
            if "gate" in row and "median_s" in row["gate"] and "median_s" in row["open"]:
                row["ratio"] = round(row["gate"]["median_s"] / row["open"]["median_s"], 2)
            rows.append(row)
            g, o = row.get("gate", {}), row.get("open", {})
            print(f"{kind:9s} drops {drops}: gate median {g.get('median_s', '-')} s max "
                  f"{g.get('max_s', '-')} s naks {g.get('naks', '-')} | open median "
                  f"{o.get('median_s', '-')} s max {o.get('max_s', '-')} s | ratio {row.get('ratio', '-')}",
                  flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"pushes": args.pushes, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
