"""`gyrocal demo`: the main job on the embedded default, in under a minute, with no hardware.

It starts the virtual strapdown unit as a separate process (on a pty, or on a python-can
udp_multicast bus with ``--can``), runs the daemon's engine against it, lets the unit tumble through
its poses until the estimator converges and validates, pushes the set, waits for the ack and the
read-back, and then asks the unit, which knows its own truth, how much drift is left in its
compensated output. Exit status 0 means the set was pushed, acked and lowered the drift on every axis.

``--mavlink`` calibrates a virtual PX4 and a virtual ArduPilot autopilot instead, and prints the gyro
offset error before and after over the temperature range seen, in deg/h (gyrocal/mavlink/demo.py).

``--grade fibre|tactical|consumer`` runs a unit of that grade (gyrocal/sim/grades.py) instead of the
demo's; the JSON then gains ``grade`` and ``predicted_drift_after`` (the drift the daemon predicted
the set would leave, deg/s per axis, beside the measured ``drift_rms_after``) to Contract 4's keys.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from gyrocal.daemon.config import load_config
from gyrocal.daemon.engine import Engine
from gyrocal.daemon.logsetup import setup_logging
from gyrocal.daemon.virtual import VirtualUnitProcess, free_udp_port, start_virtual_unit

log = logging.getLogger("gyrocal.demo")
DPH = 3600.0


def predicted_left(pred: dict[str, Any] | None) -> dict[str, Any] | None:
    """The drift a pushed set was expected to leave [deg/h]: the poses seen and the sphere mixed in the
    share of rests at poses not seen yet (``expected``); for an older record, ``left`` or the poses seen."""
    pred = pred or {}
    return pred.get("expected") or pred.get("left") or pred.get("left_poses")


def open_engine_and_unit(cfg: Any, kind: str, work: Path,
                         node_id: int = 0) -> tuple[Engine, VirtualUnitProcess]:
    """The daemon's engine and a virtual unit process (pty or CAN ``udp_multicast``), connected.

    On a bus the engine listens before the unit switches on, or its HELLO goes unheard; on a pty the
    unit comes first, since its port is the engine's link. A failure leaves nothing running."""
    engine = unit = None
    try:
        if kind == "can":
            can_port = free_udp_port()
            engine = Engine(cfg, {**cfg.link, "kind": "can", "can_node_id": node_id,
                                  "can": {"interface": "udp_multicast", "channel": "239.74.163.2",
                                          "port": can_port}})
            engine.open()
            unit = start_virtual_unit(cfg.virtual_unit, kind, work / "unit", can_port=can_port)
        else:
            unit = start_virtual_unit(cfg.virtual_unit, kind, work / "unit")
            engine = Engine(cfg, {**cfg.link, **unit.link_cfg})
            engine.open()
    except BaseException:
        if engine is not None:
            engine.close()
        if unit is not None:
            unit.stop()
        raise
    return engine, unit


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--can", action="store_true", help="use a python-can udp_multicast bus, not a pty")
    p.add_argument("--seed", type=int, default=1, help="the virtual unit's seed (its truth and bias)")
    p.add_argument("--rate", type=float, default=1000.0, help="sample rate [Hz], up to 2000")
    p.add_argument("--grade", choices=("demo", "fibre", "tactical", "consumer"), default="demo",
                   help="the virtual unit's grade (default: the demo's unit)")
    p.add_argument("--can-node-id", type=int, default=0, metavar="N", help="the unit's CAN node id (--can)")
    p.add_argument("--timeout", type=float, default=150.0, help="give up after this many seconds")
    p.add_argument("--latitude", type=float, default=None, metavar="DEG",
                   help="the virtual unit turns with the Earth at this latitude, and the daemon is told it "
                        "(site.latitude_deg): it finds north from the tumble and takes the Earth's rotation "
                        "out (default: an Earth that does not turn)")
    p.add_argument("--heading", type=float, default=30.0, metavar="DEG",
                   help="with --latitude: the unit's heading at switch-on, east of north (default 30)")
    p.add_argument("--mavlink", action="store_true",
                   help="calibrate a virtual PX4 and ArduPilot over MAVLink instead (docs/mavlink.md)")
    p.add_argument("--autopilot", choices=("px4", "ardupilot", "both"), default="both",
                   help="with --mavlink: which virtual autopilot(s)")
    p.add_argument("--json", action="store_true", help="print Contract 4 JSON instead of a table")
    p.add_argument("--verbose", action="store_true", help="show the daemon's log lines")


def _pushed(engine: Engine) -> bool:
    s = engine.session
    return s is not None and bool(s.last_push)


def run_demo(kind: str, seed: int, rate_hz: float, timeout_s: float, grade: str = "demo",
             node_id: int = 0, latitude_deg: float | None = None,
             heading_deg: float = 30.0) -> dict[str, Any]:
    """Run the whole flow and return Contract 4's figures plus a few details for the table."""
    with tempfile.TemporaryDirectory(prefix="gyrocal-demo-") as tmp:
        work = Path(tmp)
        extra = ["--grade", grade] + (["--can-node-id", str(node_id)] if kind == "can" else [])
        if latitude_deg is not None:
            extra += ["--latitude", str(latitude_deg), "--heading", str(heading_deg)]
        cfg = load_config(None, {
            "state_dir": str(work / "state"), "control_socket": str(work / "control.sock"),
            "virtual_unit.seed": seed, "virtual_unit.rate_hz": rate_hz, "link.kind": kind,
            "virtual_unit.extra_args": extra, "link.can_node_id": node_id, "site.latitude_deg": latitude_deg,
        })
        started = time.monotonic()
        unit = None
        engine = None
        try:
            engine, unit = open_engine_and_unit(cfg, kind, work, node_id)
            before: dict[str, Any] = {}
            push_at: dict[str, float] = {}

            def until(e: Engine) -> bool:
                if not before and e.session is not None and e.session.applied is not None:
                    before.update(unit.status())  # what the unit's output holds before the push
                    push_at["hello"] = time.monotonic()
                if _pushed(e) and "hello" in push_at:
                    push_at["t"] = round(time.monotonic() - push_at["hello"], 1)
                return _pushed(e)

            engine.run(until=until, timeout_s=timeout_s)
            session = engine.session
            push = session.last_push if session is not None else {}
            time.sleep(0.3)  # let the unit write its status after applying the set
            after = unit.status()
            elapsed = time.monotonic() - started
            status = dict(engine.status)
        finally:
            if engine is not None:
                engine.close()
            if unit is not None:
                unit.stop()
    acked = push.get("status") == "acked"
    before_rms = before.get("drift_rms_compensated_dps") or after.get("drift_rms_raw_dps") or {}
    after_rms = (after.get("drift_rms_compensated_dps") or {}) if acked else before_rms
    return {
        "pushed": bool(push), "acked": acked, "version": push.get("version"), "link": kind,
        "drift_rms_before": before_rms, "drift_rms_after": after_rms,
        "readback_ok": bool(push.get("readback_ok")), "elapsed_s": round(elapsed, 1),
        "unit_serial": (status.get("unit") or {}).get("serial"), "state": status.get("state"),
        "reason": status.get("reason"), "samples": status.get("samples"), "grade": grade,
        "predicted_drift_after": _dps(predicted_left(push.get("predicted_drift_dph"))),
        "first_push_s": push_at.get("t"),
    }


def _dps(v: dict[str, Any] | None) -> dict[str, float | None]:
    """{x, y, z} deg/h (None where unknown) as deg/s, the unit of Contract 4's figures."""
    return {a: (v[a] / DPH if v and v.get(a) is not None else None) for a in "xyz"} if v else {}


def main(args: argparse.Namespace) -> int:
    setup_logging("INFO" if args.verbose else "WARNING")
    if args.mavlink:
        from gyrocal.mavlink import demo as mavlink_demo  # needs the mavlink extra (pymavlink)

        kinds = ("px4", "ardupilot") if args.autopilot == "both" else (args.autopilot,)
        return mavlink_demo.main(args.seed, args.timeout, args.json, kinds)
    res = run_demo("can" if args.can else "serial", args.seed, args.rate, args.timeout, args.grade,
                   args.can_node_id, args.latitude, args.heading)
    before, after = res["drift_rms_before"], res["drift_rms_after"]
    improved = bool(before and after) and all(after[a] < before[a] for a in "xyz")
    if args.json:
        keys = ("pushed", "acked", "version", "link", "drift_rms_before", "drift_rms_after", "grade",
                "predicted_drift_after")
        print(json.dumps({k: res[k] for k in keys}, indent=2))
    else:
        _print_table(res)
    if not (res["acked"] and improved):
        print(f"gyrocal demo: no improvement pushed ({res['state']}: {res['reason']})", file=sys.stderr)
        return 1
    return 0


def _print_table(res: dict[str, Any]) -> None:
    before, after = res["drift_rms_before"], res["drift_rms_after"]
    print(f"gyrocal demo: virtual unit {res['unit_serial']} ({res['grade']} grade) over {res['link']}, "
          f"{res['samples']} samples in {res['elapsed_s']} s; first push {res['first_push_s']} s after HELLO")
    print(f"calibration v{res['version']}: pushed={res['pushed']} acked={res['acked']} "
          f"read back={res['readback_ok']}")
    pred = res["predicted_drift_after"]
    print("axis  drift RMS before [deg/h]  after [deg/h]  reduction  predicted after [deg/h]")
    for a in "xyz":
        if a in before and a in after:
            b, f = before[a] * DPH, after[a] * DPH
            p = f"{pred[a] * DPH:23.3f}" if pred.get(a) is not None else f"{'-':>23}"
            print(f"{a:>4}  {b:24.3f}  {f:13.3f}  {b / max(f, 1e-12):8.1f}x  {p}")
    print("(drift = the unit's systematic output drift over the schedule's poses, noise excluded, "
          "as the virtual unit measures it from its truth model)")
