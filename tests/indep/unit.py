"""An independent strapdown unit, built from docs/protocol.md alone, to test the daemon against.

    python -m tests.indep.unit --link pty --rate 400 --grade fibre --flash F.json --status S.json
    python -m tests.indep.unit --link can --can-port 43113 --node 3 --rate 400 ...

The first line on stdout is the pty path (serial) or the bus description (CAN). SIGUSR1 power-cycles
the unit (it goes dark for --off-s, then switches on: boot counter + 1, new bias, HELLO); SIGTERM
stops it. The flash file keeps the boot counter and the applied set across power cycles and runs.
The status JSON (rewritten twice a second and at every event) gives the truth: the drift RMS over
the session's poses before and after the applied compensation [deg/s], white noise excluded.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import signal
import sys
import time
from pathlib import Path

import numpy as np

from tests.indep import wire
from tests.indep.links import CanLink, PtyLink
from tests.indep.truth import GRADES, PoseSchedule, Truth, temperature
from tests.indep.wire import CoeffSet, TempRateRule

FIRMWARE = (3, 1, 4)
COEFF_LIMIT_DPS = 50.0  # the largest coefficient magnitude this unit's fixed-point path can apply


class Unit:
    """The unit's firmware: switch-on, sample loop, and the COEFF_* / HELLO_REQUEST handlers."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.rate = args.rate
        self.events: queue.Queue = queue.Queue()
        if args.link == "pty":
            self.link: PtyLink | CanLink = PtyLink(self.events)
        else:
            kwargs = {"interface": args.can_interface, "channel": args.can_channel}
            if args.can_port:
                kwargs["port"] = args.can_port
            self.link = CanLink(self.events, args.node, kwargs)
        self.flash_path = Path(args.flash)
        flash = json.loads(self.flash_path.read_text()) if self.flash_path.exists() else {}
        self.boot = int(flash.get("boot", 0))
        self.applied = CoeffSet.decode(bytes.fromhex(flash["set"])) if "set" in flash else CoeffSet.empty()
        self.truth = Truth.for_unit(args.serial, args.grade, args.noise, args.temp_slope)
        self.busy_next = args.busy_next
        self.cycle_requested = False
        self.log: dict = {"acks": [], "naks": [], "reads": 0, "hello_requests": 0, "boots": [],
                          "dropped_writes": 0}
        self._last_status = 0.0

    # --- flash ----------------------------------------------------------------------------------
    def _save_flash(self) -> None:
        tmp = self.flash_path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"boot": self.boot, "set": self.applied.encode().hex()}))
        os.replace(tmp, self.flash_path)

    # --- switch-on ------------------------------------------------------------------------------
    def switch_on(self) -> None:
        self.boot += 1
        self._save_flash()
        seed = self.args.seed * 100_003 + self.boot
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.truth.new_bias(self.args.grade, rng)
        self.schedule = PoseSchedule(seed)
        self.temp0 = float(rng.uniform(18.0, 28.0))
        self.temp_rule = TempRateRule(self.args.dtemp_lag_s)
        self.seq = 0
        self.t_on = time.monotonic()
        self.anchor_next = True
        self.last_temp = self.temp0
        self.last_dtemp = 0.0
        self.log["boots"].append({"boot": self.boot, "wall": time.time(),
                                  "bias_dps": self.truth.bias.tolist()})
        self.link.send_hello(self.args.serial, FIRMWARE, self.boot, self.rate)

    def power_cycle(self) -> None:
        """Dark for --off-s: nothing is sent and whatever the host sends is lost, then switch-on."""
        self.link.flush()
        time.sleep(self.args.off_s)
        while not self.events.empty():
            self.events.get_nowait()
        self.switch_on()

    # --- host messages --------------------------------------------------------------------------
    def handle(self, event: tuple) -> None:
        kind = event[0]
        if kind == "hello_request":
            self.log["hello_requests"] += 1
            self.link.send_hello(self.args.serial, FIRMWARE, self.boot, self.rate)
            self.anchor_next = True
        elif kind == "read":
            self.log["reads"] += 1
            self.link.send_report(self.applied)
        elif kind == "write_failed":
            _, version, crc, reason = event
            self._nak(version, crc, reason)
        elif kind == "write":
            self._write(event[1])
        self.write_status()

    def _nak(self, version: int, crc: int, reason: int) -> None:
        self.log["naks"].append({"version": version, "reason": reason, "boot": self.boot,
                                 "wall": time.time()})
        self.link.send_nak(version, crc, reason)

    def _write(self, cset: CoeffSet) -> None:
        crc = cset.crc
        names = wire.TERM_TABLE.get(cset.terms_id)
        if names is None:
            return self._nak(cset.version, crc, wire.NAK_UNKNOWN_TERMS)
        if cset.n != len(names):
            return self._nak(cset.version, crc, wire.NAK_BAD_LENGTH)
        if not np.all(np.isfinite(cset.coeffs)) or np.any(np.abs(cset.coeffs) > COEFF_LIMIT_DPS):
            return self._nak(cset.version, crc, wire.NAK_OUT_OF_RANGE)
        if self.busy_next > 0:
            self.busy_next -= 1
            return self._nak(cset.version, crc, wire.NAK_BUSY)
        # applied atomically between two samples: the ACK goes out before the next SAMPLE, which is
        # the first compensated with the new set (doc sec. 6)
        self.applied = cset
        self._save_flash()
        self.link.send_ack(cset.version, self.applied.crc)
        rms = self.drift_rms()
        self.log["acks"].append({"version": cset.version, "crc": self.applied.crc, "boot": self.boot,
                                 "seq_first": self.seq, "wall": time.time(),
                                 "rms_before": rms["before"], "rms_after": rms["after"]})
        return None

    # --- samples --------------------------------------------------------------------------------
    def _compensation(self, accel: np.ndarray, temp: np.ndarray, dtemp: np.ndarray, t_s: np.ndarray,
                      cset: CoeffSet) -> np.ndarray:
        if cset.n == 0:
            return np.zeros((len(accel), 3))
        names = wire.TERM_TABLE[cset.terms_id]
        return wire.evaluate_terms(names, accel, temp, dtemp, t_s) @ cset.coeffs.T

    def emit(self, count: int) -> None:
        """Send ``count`` samples from seq onwards, compensated with the set applied now."""
        k = self.seq + np.arange(count)
        t_us = np.round(k * 1e6 / self.rate).astype(np.int64)
        t_s = t_us / 1e6
        rate, force = self.schedule.state(t_s)
        temp_true = temperature(t_s, self.temp0)
        g_true = force / np.linalg.norm(force, axis=1, keepdims=True)
        noise = self.rng.normal(0, self.truth.noise_dps, (count, 3))
        raw = rate + self.truth.drift(g_true, temp_true) + noise
        lsb = self.link.accel_lsb_g
        accel = np.round((force + self.rng.normal(0, self.truth.accel_noise_g, (count, 3))) / lsb) * lsb
        temp = np.round(temp_true / 0.01) * 0.01  # as sent
        dtemp = np.array([self.temp_rule.step(float(t), float(c)) for t, c in zip(t_s, temp, strict=True)])
        out = raw - self._compensation(accel, temp, dtemp, t_s, self.applied)
        self.link.send_samples(self.seq, t_us, out, accel, temp, self.anchor_next)
        self.anchor_next = False
        self.seq += count
        self.last_temp, self.last_dtemp = float(temp[-1]), float(dtemp[-1])

    # --- truth for the checks -------------------------------------------------------------------
    def drift_rms(self) -> dict:
        """RMS [deg/s] over the session's poses of the true drift, before and after the applied set."""
        g = self.schedule.gravity_at_poses()
        temp = np.full(len(g), self.last_temp)
        true = self.truth.drift(g, temp)
        comp = self._compensation(g, temp, np.full(len(g), self.last_dtemp), np.zeros(len(g)), self.applied)
        axes = "xyz"
        before = np.sqrt(np.mean(true ** 2, axis=0))
        after = np.sqrt(np.mean((true - comp) ** 2, axis=0))
        return {"before": dict(zip(axes, before.tolist(), strict=True)),
                "after": dict(zip(axes, after.tolist(), strict=True))}

    def write_status(self) -> None:
        self._last_status = time.monotonic()
        if not self.args.status:
            return
        rms = self.drift_rms()
        status = {
            "serial": self.args.serial, "boot": self.boot, "seq": self.seq, "rate_hz": self.rate,
            "link": self.link.describe(), "grade": self.args.grade, "noise_dps": self.truth.noise_dps,
            "applied": {"version": self.applied.version, "terms_id": self.applied.terms_id,
                        "crc": self.applied.crc, "coefficients": self.applied.coeffs.tolist()},
            "drift_rms_before": rms["before"], "drift_rms_after": rms["after"],
            "bias_dps": self.truth.bias.tolist(), "rx": self.link.stats(), **self.log,
        }
        path = Path(self.args.status)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(status))
        os.replace(tmp, path)

    # --- main loop ------------------------------------------------------------------------------
    def run(self, stop: list[bool]) -> None:
        print(self.link.describe(), flush=True)
        time.sleep(self.args.start_delay)  # powered later than its port appears: the host hears HELLO
        self.switch_on()
        block = max(1, self.rate // 100)  # up to 10 ms of samples between two looks at the host
        while not stop[0]:
            if self.cycle_requested:
                self.cycle_requested = False
                self.power_cycle()
            while not self.events.empty():
                self.handle(self.events.get_nowait())
            due = int((time.monotonic() - self.t_on) * self.rate) + 1
            if due > self.seq:
                self.emit(min(block, due - self.seq))
                continue
            self.link.flush()
            if time.monotonic() - self._last_status > 0.5:
                self.write_status()
            try:
                self.handle(self.events.get(timeout=min(0.005, (self.seq + 1) / self.rate
                                                        - (time.monotonic() - self.t_on))))
            except (queue.Empty, ValueError):
                pass
        self.write_status()
        self.link.close()


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m tests.indep.unit", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--link", choices=["pty", "can"], default="pty")
    p.add_argument("--rate", type=int, default=400, help="sample rate [Hz]")
    p.add_argument("--grade", choices=sorted(GRADES), default="fibre")
    p.add_argument("--noise", type=float, default=None, help="white gyro noise per sample [deg/s]")
    p.add_argument("--temp-slope", type=float, default=0.0, help="drift per degC [deg/s/degC]")
    p.add_argument("--serial", type=int, default=0x5EED0042)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--flash", required=True, help="JSON file standing in for the unit's flash")
    p.add_argument("--status", default="", help="status JSON written by the unit (truth)")
    p.add_argument("--off-s", type=float, default=0.5, help="dark time of a power cycle [s]")
    p.add_argument("--start-delay", type=float, default=0.0,
                   help="dark time before the first switch-on [s] (the pty exists already)")
    p.add_argument("--dtemp-lag-s", type=int, default=0,
                   help="diagnostic: apply the dtemp of N whole seconds earlier than doc sec. 6 says")
    p.add_argument("--busy-next", type=int, default=0, help="answer the next N good writes BUSY")
    p.add_argument("--node", type=int, default=0, choices=range(16))
    p.add_argument("--can-interface", default="udp_multicast")
    p.add_argument("--can-channel", default="239.74.163.2")
    p.add_argument("--can-port", type=int, default=0)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    unit = Unit(args)
    stop = [False]

    def on_term(_sig: int, _frm: object) -> None:
        stop[0] = True

    def on_usr1(_sig: int, _frm: object) -> None:
        unit.cycle_requested = True

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    signal.signal(signal.SIGUSR1, on_usr1)
    unit.run(stop)
    return 0


if __name__ == "__main__":
    sys.exit(main())
