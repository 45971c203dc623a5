"""The fault campaign (issue 8): real processes, real faults, and whether the daemon survives them.

    .venv/bin/python benchmarks/faults.py [--quick] [--json OUT.json] [--only NAME[,NAME]] [--skip-can]

Each scenario starts ``gyrocal run --config`` and ``gyrocal sim`` as separate processes, on a pty or
on a python-can ``udp_multicast`` bus, and touches them only as an operator or the world would:
the sim's fault switches (``--nak-next``, ``--lose-ack``, ``--nan-readback``, ...), signals
(SIGKILL, SIGUSR1 power cycle, SIGUSR2 silence, SIGHUP cable replug), the control socket, and the
state directory on disk. For each scenario it reports:

- tried: what was done;
- up: whether the daemon process stayed up the whole time (never exited, never restarted);
- lost: what was lost (samples the decoder counted lost, sessions started beyond the switch-ons,
  store versions minted);
- recover_s: the time from the end of the fault (the unit back, the store writable, ...) until the
  daemon was healthy again (connected, samples flowing, the session learning), where that applies;
- agree: at the end, whether the store and the unit agree: the unit's applied version (its own
  status file) is stored with a push status the unit verifiably held ('acked' / 'applied_ack_lost')
  and the same CRC, and no push is left 'pending';
- ok: the scenario's own pass rule (also the acceptance: up, agree, recover_s <= 2 s where timed).

Times are measured on a loaded 2-core machine; they are figures, not assertions. ``--quick`` runs
the fast scenarios on the pty only (what tests/test_faults.py also runs).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_store's records (long_history)

from gyrocal.daemon.control import request  # noqa: E402
from gyrocal.daemon.reconcile import record_crc  # noqa: E402
from gyrocal.daemon.store import APPLIED_STATUSES, CalibrationStore  # noqa: E402
from gyrocal.sim.schedule import tumble  # noqa: E402

PY = [sys.executable, "-m", "gyrocal.cli"]
SERIAL = 4242
GROUP = "239.74.163.2"


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


@dataclass
class Result:
    name: str
    link: str
    tried: str
    up: bool = False
    lost: str = ""
    recover_s: float | None = None
    agree: bool | None = None
    ok: bool = False
    notes: list[str] = field(default_factory=list)
    wall_s: float = 0.0


class Rig:
    """One daemon and one virtual unit in a temporary directory, on ``link`` ('pty' or 'can')."""

    def __init__(self, tmp: Path, link: str, rate: float = 500.0) -> None:
        self.tmp, self.link, self.rate = tmp, link, rate
        self.sock = tmp / "control.sock"
        self.pty = tmp / "unit.pty"
        self.flash = tmp / "flash.json"
        self.unit_json = tmp / "unit.json"
        self.state = tmp / "state"
        self.port = free_udp_port()
        self.daemon: subprocess.Popen[bytes] | None = None
        self.sim: subprocess.Popen[bytes] | None = None
        self.daemon_starts = 0
        # rests of 1.5 s: the still rule keeps a rest only past window + 2 margins + min_run (1.1 s),
        # so the 0.8 s rests used before it gave no still data and no push at all
        sched = tumble(1.5, 0.25)
        self.schedule = tmp / "schedule.yaml"
        self.schedule.write_text(yaml.safe_dump({"dwell_s": sched.dwell_s, "move_s": sched.move_s,
                                                 "poses": sched.poses_g.tolist()}))

    # -- processes ---------------------------------------------------------------------------
    def link_cfg(self) -> dict[str, Any]:
        if self.link == "pty":
            return {"kind": "serial", "url": str(self.pty)}
        return {"kind": "can", "can": {"interface": "udp_multicast", "channel": GROUP, "port": self.port}}

    def start_daemon(self, **sections: Any) -> None:
        cfg = {"link": self.link_cfg(), "virtual_unit": {"enabled": False}, "state_dir": str(self.state),
               "control_socket": str(self.sock), "validation": {"block_s": 0.25}, **sections}
        path = self.tmp / "gyrocal.yaml"
        path.write_text(yaml.safe_dump(cfg))
        log = (self.tmp / "daemon.log").open("a")
        self.daemon = subprocess.Popen([*PY, "run", "--config", str(path)], stdout=log,
                                       stderr=subprocess.STDOUT)
        self.daemon_starts += 1

    def start_sim(self, *faults: str) -> None:
        cmd = [*PY, "sim", "--rate", str(self.rate), "--seed", "3", "--schedule", str(self.schedule),
               "--status-json", str(self.unit_json), "--flash", str(self.flash), *faults]
        if self.link == "pty":
            cmd += ["--link", "pty", "--pty-link", str(self.pty)]
        else:
            cmd += ["--link", "can", "--can-interface", "udp_multicast", "--can-channel", GROUP,
                    "--can-port", str(self.port)]
        err = (self.tmp / "sim.stderr").open("a")
        self.sim = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)

    def start_healthy(self) -> bool:
        """Start the daemon and a fault-free unit; True once the daemon is healthy (within 30 s)."""
        self.start_daemon()
        self.start_sim()
        return self.wait(self.healthy, 30)

    def unit_back(self, timeout_s: float = 20.0) -> float:
        """Wait until the restarted unit is there again (its pty exists, or it wrote its status on
        CAN); returns that moment (monotonic s): recovery is timed from it, not from process spawn."""
        end = time.monotonic() + timeout_s
        pid = self.sim.pid if self.sim is not None else None
        while time.monotonic() < end:
            if self.link == "pty" and self.pty.exists():
                return time.monotonic()
            if self.link == "can" and self.unit().get("pid") == pid:
                return time.monotonic()
            time.sleep(0.01)
        return time.monotonic()

    def kill_sim(self) -> None:
        self.pty.unlink(missing_ok=True)
        if self.sim is not None and self.sim.poll() is None:
            self.sim.kill()
            self.sim.wait(10)

    def signal_sim(self, sig: int) -> None:
        if self.sim is not None and self.sim.poll() is None:
            self.sim.send_signal(sig)

    def daemon_up(self) -> bool:
        return self.daemon is not None and self.daemon.poll() is None

    def close(self) -> None:
        for proc in (self.daemon, self.sim):
            if proc is None or proc.poll() is not None:
                continue
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)

    # -- observation -------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        try:
            return request(self.sock, {"cmd": "status"}, timeout=5.0)
        except Exception:
            return {}

    def command(self, req: dict[str, Any]) -> dict[str, Any]:
        try:
            return request(self.sock, req, timeout=15.0)
        except Exception as err:
            return {"ok": False, "error": str(err)}

    def unit(self) -> dict[str, Any]:
        try:
            return json.loads(self.unit_json.read_text())
        except (OSError, ValueError):
            return {}

    def wait(self, pred: Callable[[], Any], timeout_s: float, poll_s: float = 0.05) -> Any:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            try:
                v = pred()
            except Exception:
                v = None
            if v:
                return v
            if not self.daemon_up():
                return None
            time.sleep(poll_s)
        return None

    def healthy(self) -> bool:
        """Connected, samples flowing, a session that has read the unit's set."""
        st = self.status()
        live = st.get("liveness") or {}
        return (bool(st.get("link", {}).get("connected")) and live.get("sample_age_s") is not None
                and live["sample_age_s"] < 0.5 and st.get("applied") is not None
                and st.get("state") not in ("WAIT_UNIT", "UNIT_SILENT", "WAIT_HELLO"))

    def acked(self, version: int | None = None) -> dict[str, Any] | None:
        st = self.status()
        push = st.get("last_push") or {}
        if push.get("status") == "acked" and (version is None or push.get("version") != version):
            return st
        return None

    def records(self) -> list[Any]:
        return CalibrationStore(self.state).history(SERIAL) if (self.state / "units").exists() else []

    def agree(self) -> tuple[bool, str]:
        """The unit's applied set against the store (see the module doc)."""
        u = self.unit()
        recs = self.records()
        pending = [r.version for r in recs if r.push.get("status") == "pending"]
        ver = u.get("applied_version")
        if ver is None:
            applied = [r.version for r in recs if r.push.get("status") in APPLIED_STATUSES]
            ok = not pending
            return ok, f"unit holds no set; store applied {applied}; pending {pending}"
        rec = next((r for r in recs if r.version == ver), None)
        if rec is None:
            return False, f"unit holds v{ver}, unknown to the store"
        status = rec.push.get("status")
        crc_ok = record_crc(rec) == u.get("applied_crc")
        ok = status in APPLIED_STATUSES and crc_ok and not pending
        return ok, f"unit v{ver}; store says {status!r}, crc {'=' if crc_ok else '!='}; pending {pending}"

    def lost_samples(self) -> int:
        return int(((self.status().get("link") or {}).get("errors") or {}).get("lost_samples", 0))


# ---- scenarios --------------------------------------------------------------------------------
PUSH_S = 120.0  # generous bound for a first push at 500 Hz on a loaded machine


def _finish(rig: Rig, res: Result, *, need_agree: bool = True) -> Result:
    res.up = rig.daemon_up() and rig.daemon_starts == 1
    ok, why = rig.agree()
    res.agree = ok
    res.notes.append(why)
    if need_agree and not ok:
        res.ok = False
    return res


def sc_start_without_unit(rig: Rig) -> Result:
    res = Result("start_without_unit", rig.link,
                 "daemon started 3 s before the unit exists; then the unit appears")
    rig.start_daemon()
    rig.wait(rig.status, 30)  # the daemon is up and answering (its start-up takes ~1-2 s)
    time.sleep(3.0)
    st = rig.status()
    res.notes.append(f"before: {st.get('state')}: {st.get('reason')}")
    rig.start_sim()
    t0 = rig.unit_back()
    ok = rig.wait(rig.healthy, 30)
    res.recover_s = round(time.monotonic() - t0, 2) if ok else None
    res.lost = "nothing"
    res.ok = bool(ok) and st.get("state") in ("WAIT_UNIT", "WAIT_HELLO") and rig.daemon_up()
    return _finish(rig, res)


def sc_unplug_mid_push(rig: Rig) -> Result:
    res = Result("unplug_mid_push", rig.link,
                 "the unit vanishes (SIGKILL) while a push waits for its ack; back 3 s later")
    rig.start_daemon()
    rig.start_sim("--drop-acks", "2")  # the first push waits for acks that never come
    if not rig.wait(lambda: rig.status().get("state") == "PUSHING", PUSH_S):
        res.notes.append("no push started")
        return _finish(rig, res)
    rig.kill_sim()
    time.sleep(3.0)
    alive_while_gone = rig.daemon_up()
    st = rig.status()
    res.notes.append(f"while gone: {st.get('state')}: {st.get('reason')}")
    rig.start_sim()
    t0 = rig.unit_back()
    ok = rig.wait(rig.healthy, 30)
    res.recover_s = round(time.monotonic() - t0, 2) if ok else None
    acked = rig.wait(rig.acked, PUSH_S)
    sessions = rig.status().get("sessions")
    res.lost = f"the first push (the unit was gone); sessions {sessions} for 2 switch-ons"
    res.ok = alive_while_gone and bool(ok) and bool(acked) and sessions == 2
    return _finish(rig, res)


def sc_nan_readback(rig: Rig) -> Result:
    res = Result("nan_readback", rig.link,
                 "the unit answers its first 3 COEFF_READs with NaN (valid frame CRC)")
    rig.start_daemon()
    rig.start_sim("--nan-readback", "3")
    learning = rig.wait(lambda: rig.status().get("trained_samples", 0) > 0, 60)
    acked = rig.wait(rig.acked, PUSH_S)
    st = rig.status()
    errs = (st.get("link") or {}).get("errors") or {}
    res.lost = f"{errs.get('bad_values', 0)} bad report(s) dropped, counted; learning delayed"
    res.ok = bool(learning) and bool(acked)
    return _finish(rig, res)


def sc_store_unwritable(rig: Rig) -> Result:
    res = Result("store_unwritable", rig.link,
                 "the unit's store directory becomes unwritable (ENOTDIR) before the first push; "
                 "fixed 2 s after the daemon said so")
    if not rig.start_healthy():
        res.notes.append("never healthy")
        return _finish(rig, res)
    udir = rig.state / "units" / str(SERIAL)
    aside = rig.state / "aside"
    if udir.exists():
        udir.rename(aside)
    udir.parent.mkdir(parents=True, exist_ok=True)
    udir.write_text("not a directory\n")  # root ignores modes: a file in the way fails every write
    said = rig.wait(lambda: "store unavailable" in json.dumps(rig.status()), PUSH_S)
    st = rig.status()
    pushed_meanwhile = (st.get("last_push") or {}).get("status") is not None
    time.sleep(2.0)
    udir.unlink()
    if aside.exists():
        aside.rename(udir)
    t0 = time.monotonic()
    acked = rig.wait(rig.acked, 60)
    res.recover_s = round(time.monotonic() - t0, 2) if acked else None
    res.lost = "pushes deferred while the store was unwritable"
    res.ok = bool(said) and not pushed_meanwhile and bool(acked)
    res.notes.append(f"said: {bool(said)}; pushed while unwritable: {pushed_meanwhile}")
    return _finish(rig, res)


def sc_refused_pushes(rig: Rig) -> Result:
    res = Result("refused_pushes", rig.link,
                 "push a 22-term set, a NaN set, an unknown term set, then a good file set, over the socket")
    if not rig.start_healthy():
        return _finish(rig, res)
    names = ["1", "gx", "gy", "gz", "gx^2", "gy^2", "gz^2", "gx*gy", "gy*gz", "gx*gz"]
    bad = [
        {"cmd": "push", "terms": [f"t{k}" for k in range(22)], "coefficients": [[0.0] * 22] * 3},
        {"cmd": "push", "terms": names, "coefficients": [[float("nan")] * 10] * 3},
        {"cmd": "push", "terms": ["1", "foo"], "coefficients": [[0.0, 0.0]] * 3},
        {"cmd": "rollback", "to": 99},
    ]
    refused = [not rig.command(b).get("ok") for b in bad]
    good = rig.command({"cmd": "push", "terms": names, "coefficients": [[0.001] + [0.0] * 9] * 3})
    acked = rig.wait(lambda: (rig.status().get("last_push") or {}).get("status") == "acked", 30)
    res.lost = "nothing"
    res.ok = all(refused) and bool(good.get("ok")) and bool(acked)
    res.notes.append(f"refused {sum(refused)}/{len(refused)}; good push {good}")
    return _finish(rig, res)


def sc_ack_lost(rig: Rig) -> Result:
    res = Result("ack_lost", rig.link, "the unit applies the first 3 writes but every ack is lost")
    rig.start_daemon()
    rig.start_sim("--lose-ack", "3")
    ended = rig.wait(lambda: (rig.status().get("last_push") or {}).get("status") not in (None,), PUSH_S)
    agree = rig.wait(lambda: rig.agree()[0] and (rig.status().get("unit_set") or {}).get("agree"), 30)
    st = rig.status()
    last = st.get("last_push") or {}
    res.lost = f"the ack of v{last.get('version')} (push ended {last.get('status')!r})"
    res.ok = bool(ended) and bool(agree)
    res.notes.append(f"daemon view: {st.get('unit_set')}")
    return _finish(rig, res)


def sc_cycle_after_ack(rig: Rig) -> Result:
    res = Result("cycle_after_ack", rig.link, "the unit power-cycles right after its first ack")
    rig.start_daemon()
    rig.start_sim("--cycle-after-ack", "1")
    second = rig.wait(lambda: (rig.status().get("unit") or {}).get("boot_count", 0) >= 2
                      and rig.status().get("applied") is not None, PUSH_S)
    agree = rig.wait(lambda: rig.agree()[0], 30)
    st = rig.status()
    res.lost = f"the read-back of the pushed set; sessions {st.get('sessions')} for 2 switch-ons"
    res.ok = bool(second) and bool(agree) and st.get("sessions") == 2
    return _finish(rig, res)


def sc_daemon_killed_mid_push(rig: Rig) -> Result:
    res = Result("daemon_killed_mid_push", rig.link,
                 "SIGKILL of the daemon while a push waits (ack dropped), then restarted (as systemd would)")
    rig.start_daemon()
    rig.start_sim("--drop-acks", "1")
    if not rig.wait(lambda: rig.status().get("state") == "PUSHING", PUSH_S):
        return _finish(rig, res)
    assert rig.daemon is not None
    rig.daemon.kill()
    rig.daemon.wait(10)
    t0 = time.monotonic()
    rig.start_daemon()
    ok = rig.wait(rig.healthy, 30)
    res.recover_s = round(time.monotonic() - t0, 2) if ok else None
    rig.wait(lambda: rig.acked() or None, PUSH_S)
    pend = [r.version for r in rig.records() if r.push.get("status") == "pending"]
    res.lost = "the killed push (closed as 'abandoned' at restart)"
    res.ok = bool(ok) and not pend
    res = _finish(rig, res)
    res.up = rig.daemon_up() and rig.daemon_starts == 2  # restarted once, by design
    return res


def sc_busy_storm(rig: Rig) -> Result:
    res = Result("busy_storm", rig.link, "the unit answers the first 12 writes with NAK BUSY")
    rig.start_daemon()
    rig.start_sim("--nak-next", "12")
    acked = rig.wait(rig.acked, 240)
    recs = rig.records()
    u = rig.unit()
    res.lost = f"{len(recs)} version(s) minted for {u.get('writes', {}).get('naked', '?')} NAKs"
    res.ok = bool(acked) and len(recs) <= 2
    return _finish(rig, res)


def sc_seq_outliers(rig: Rig) -> Result:
    res = Result("seq_outliers", rig.link, "one sample with a far sequence number every 2 s")
    rig.start_daemon()
    rig.start_sim("--seq-outlier-every", "2")
    acked = rig.wait(rig.acked, PUSH_S)
    st = rig.status()
    seq = st.get("sequence") or {}
    res.lost = f"{seq.get('outliers')} outlier sample(s) dropped; sessions {st.get('sessions')}"
    res.ok = bool(acked) and st.get("sessions") == 1 and seq.get("outliers", 0) >= 1
    return _finish(rig, res)


def sc_silence(rig: Rig) -> Result:
    res = Result("unit_silent", rig.link, "the unit stops sending for 5 s (SIGUSR2 twice), link still up")
    if not rig.start_healthy():
        return _finish(rig, res)
    rig.signal_sim(signal.SIGUSR2)
    t_silent = time.monotonic()
    seen = rig.wait(lambda: rig.status().get("state") == "UNIT_SILENT", 10)
    detect = time.monotonic() - t_silent
    time.sleep(max(0.0, 5.0 - detect))
    rig.signal_sim(signal.SIGUSR2)
    t0 = time.monotonic()
    ok = rig.wait(rig.healthy, 20)
    res.recover_s = round(time.monotonic() - t0, 2) if ok else None
    st = rig.status()
    res.lost = f"5 s of samples; sessions {st.get('sessions')}"
    res.ok = bool(seen) and bool(ok) and st.get("sessions") == 1
    res.notes.append(f"silence seen after {detect:.1f} s")
    return _finish(rig, res)


def sc_replug(rig: Rig) -> Result:
    res = Result("pty_replug", rig.link, "the cable is replugged (SIGHUP: a new pty behind the same path)")
    if not rig.start_healthy():
        return _finish(rig, res)
    before = rig.status().get("sessions")
    t0 = time.monotonic()
    rig.signal_sim(signal.SIGHUP)
    ok = rig.wait(lambda: rig.healthy() and (rig.status().get("link") or {}).get("reconnects", 0) >= 1, 20)
    res.recover_s = round(time.monotonic() - t0, 2) if ok else None
    time.sleep(2.0)
    st = rig.status()
    res.lost = f"samples during the replug; sessions {before} -> {st.get('sessions')}"
    res.ok = bool(ok) and st.get("sessions") == before
    return _finish(rig, res)


def sc_reload_storm(rig: Rig) -> Result:
    res = Result("reload_storm", rig.link,
                 "300 x systemctl reload (SIGHUP) 5 ms apart while the daemon learns, then a push")
    if not rig.start_healthy():
        return _finish(rig, res)
    t0 = time.monotonic()
    for _ in range(300):
        if rig.daemon_up():
            rig.daemon.send_signal(signal.SIGHUP)  # type: ignore[union-attr]
        time.sleep(0.005)
    ok = rig.wait(rig.healthy, 20)
    res.recover_s = round(time.monotonic() - t0 - 1.5, 2) if ok else None  # from the last signal
    acked = rig.wait(rig.acked, PUSH_S)
    text = (rig.tmp / "daemon.log").read_text(errors="replace")
    reloads = text.count("SIGHUP: configuration reloaded")
    st = rig.status()
    res.lost = (f"{reloads} reload(s) done for 300 signals (the OS merges pending ones); "
                f"sessions {st.get('sessions')}")
    res.ok = bool(ok) and bool(acked) and reloads >= 1 and st.get("sessions") == 1
    return _finish(rig, res)


def sc_power_cycles(rig: Rig) -> Result:
    res = Result("power_cycles", rig.link, "3 power cycles (SIGUSR1), 3 s apart")
    if not rig.start_healthy():
        return _finish(rig, res)
    times = []
    for _ in range(3):
        boot = (rig.unit().get("boot_count") or 0) + 1
        rig.signal_sim(signal.SIGUSR1)
        t0 = time.monotonic()

        def on_new_boot(b: int = boot) -> bool:
            return rig.healthy() and (rig.status().get("unit") or {}).get("boot_count") == b

        ok = rig.wait(on_new_boot, 20)
        times.append(time.monotonic() - t0 if ok else float("nan"))
        time.sleep(3.0)
    st = rig.status()
    res.recover_s = round(max(times), 2)
    res.lost = f"sessions {st.get('sessions')} for 4 switch-ons"
    res.ok = st.get("sessions") == 4
    return _finish(rig, res)


def sc_no_coeff_read(rig: Rig) -> Result:
    res = Result("no_coeff_read", rig.link, "the unit never answers COEFF_READ (a listen-only replay)")
    rig.start_daemon()
    rig.start_sim("--no-coeff-read")
    time.sleep(12.0)
    st = rig.status()
    log = (rig.tmp / "daemon.log").read_text(errors="replace")
    warnings = sum(1 for line in log.splitlines() if "COEFF_READ" in line and "WARNING" in line)
    res.lost = f"learning (needs the unit's set); {warnings} warning line(s) in 12 s"
    res.ok = rig.daemon_up() and "COEFF_READ" in str(st.get("reason")) and warnings <= 2
    res.notes.append(str(st.get("reason")))
    return _finish(rig, res)


def sc_flapping_cable(rig: Rig) -> Result:
    res = Result("flapping_cable", rig.link, "the cable is replugged 5 times, 1 s apart (a loose connector)")
    if not rig.start_healthy():
        return _finish(rig, res)
    before = rig.status().get("sessions")
    for _ in range(5):
        rig.signal_sim(signal.SIGHUP)
        time.sleep(1.0)
    t0 = time.monotonic()
    ok = rig.wait(rig.healthy, 20)
    res.recover_s = round(time.monotonic() - t0, 2) if ok else None
    st = rig.status()
    res.lost = f"samples while unplugged; sessions {before} -> {st.get('sessions')}"
    res.ok = bool(ok) and st.get("sessions") == before
    return _finish(rig, res)


def sc_garbage_line(rig: Rig) -> Result:
    res = Result("garbage_line", rig.link, "random garbage bursts before 5 % of the frames, through a push")
    rig.start_daemon()
    rig.start_sim("--garbage-rate", "0.05")
    acked = rig.wait(rig.acked, PUSH_S)
    errs = (rig.status().get("link") or {}).get("errors") or {}
    res.lost = f"{errs.get('garbage_bytes', 0)} garbage bytes skipped, {errs.get('crc_errors', 0)} CRC errors"
    res.ok = bool(acked)
    return _finish(rig, res)


def sc_lossy_link(rig: Rig) -> Result:
    res = Result("lossy_link", rig.link, "0.2 s of samples lost on the link in every 3 s, through a push")
    rig.start_daemon()
    rig.start_sim("--lose-burst", "0.2", "--lose-every", "3")
    acked = rig.wait(rig.acked, PUSH_S)
    lost = rig.lost_samples()
    dropped = rig.unit().get("lost_on_link", 0)
    res.lost = f"{lost} samples lost on the link, counted (the sim dropped {dropped} by the end)"
    res.ok = bool(acked) and lost > 0
    return _finish(rig, res)


HISTORY = 5000
"""Versions of the unit already in the store for ``long_history``: years of switch-ons."""


def sc_long_history(rig: Rig) -> Result:
    from bench_store import write_history

    res = Result("long_history", rig.link, f"{HISTORY:,} versions of the unit already in the store, "
                 "store.keep_versions 1000; then a push")
    udir = rig.state / "units" / str(SERIAL)
    udir.mkdir(parents=True)
    write_history(udir, HISTORY, random.Random(1), zero_coefficients=True)
    t0 = time.monotonic()
    rig.start_daemon()
    rig.start_sim()
    ok = rig.wait(rig.healthy, 60)
    up_s = time.monotonic() - t0
    acked = rig.wait(rig.acked, PUSH_S)
    kept = len(list(udir.glob("v*.json")))
    res.lost = (f"{HISTORY + 1 - kept} old versions pruned, {kept} kept; healthy {up_s:.1f} s after the "
                "daemon's start")
    res.ok = bool(ok) and bool(acked) and kept <= 1003
    return _finish(rig, res)


SCENARIOS: dict[str, tuple[Callable[[Rig], Result], tuple[str, ...], bool]] = {
    # name: (function, links, quick)
    "start_without_unit": (sc_start_without_unit, ("pty", "can"), True),
    "unplug_mid_push": (sc_unplug_mid_push, ("pty", "can"), False),
    "nan_readback": (sc_nan_readback, ("pty", "can"), False),
    "store_unwritable": (sc_store_unwritable, ("pty",), False),
    "refused_pushes": (sc_refused_pushes, ("pty",), True),
    "ack_lost": (sc_ack_lost, ("pty", "can"), False),
    "cycle_after_ack": (sc_cycle_after_ack, ("pty",), False),
    "daemon_killed_mid_push": (sc_daemon_killed_mid_push, ("pty",), False),
    "busy_storm": (sc_busy_storm, ("pty",), False),
    "seq_outliers": (sc_seq_outliers, ("pty",), False),
    "unit_silent": (sc_silence, ("pty", "can"), True),
    "pty_replug": (sc_replug, ("pty",), True),
    "reload_storm": (sc_reload_storm, ("pty",), False),
    "power_cycles": (sc_power_cycles, ("pty", "can"), True),
    "no_coeff_read": (sc_no_coeff_read, ("pty",), True),
    "flapping_cable": (sc_flapping_cable, ("pty",), True),
    "garbage_line": (sc_garbage_line, ("pty",), False),
    "lossy_link": (sc_lossy_link, ("pty", "can"), False),
    "long_history": (sc_long_history, ("pty",), False),
}


def run_one(name: str, link: str, keep: bool = False) -> Result:
    fn = SCENARIOS[name][0]
    tmp = Path(tempfile.mkdtemp(prefix=f"gyrocal-fault-{name}-"))
    rig = Rig(tmp, link)
    t0 = time.monotonic()
    try:
        res = fn(rig)
    except Exception as err:  # a harness failure is a result too, never a lost table
        res = Result(name, link, "harness error", notes=[repr(err)])
    finally:
        rig.close()
    res.wall_s = round(time.monotonic() - t0, 1)
    if not keep and res.ok:
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        res.notes.append(f"kept {tmp}")
    return res


def table(results: list[Result]) -> str:
    lines = ["| scenario | link | tried | daemon up | lost | recover [s] | store = unit | ok |",
             "|---|---|---|---|---|---|---|---|"]
    for r in results:
        rec = "-" if r.recover_s is None else f"{r.recover_s:.2f}"
        lines.append(f"| {r.name} | {r.link} | {r.tried} | {'yes' if r.up else 'NO'} | {r.lost} | {rec} | "
                     f"{'yes' if r.agree else 'NO'} | {'ok' if r.ok else 'FAIL'} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="the fast scenarios, pty only")
    p.add_argument("--only", help="comma-separated scenario names")
    p.add_argument("--skip-can", action="store_true")
    p.add_argument("--json", metavar="OUT.json")
    p.add_argument("--keep", action="store_true", help="keep every scenario's directory")
    a = p.parse_args(argv)
    names = (a.only.split(",") if a.only
             else [n for n, (_, _, quick) in SCENARIOS.items() if quick or not a.quick])
    results = []
    for name in names:
        links = ("pty",) if a.quick or a.skip_can else SCENARIOS[name][1]
        for link in links:
            r = run_one(name, link, a.keep)
            print(f"{r.name:24s} {r.link:4s} up={r.up!s:5s} ok={r.ok!s:5s} recover={r.recover_s} "
                  f"agree={r.agree} lost={r.lost} ({r.wall_s} s) {'; '.join(r.notes)}", flush=True)
            results.append(r)
    print()
    print(table(results))
    if a.json:
        Path(a.json).write_text(json.dumps([asdict(r) for r in results], indent=1) + "\n")
    return 0 if all(r.ok for r in results) else 1


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
