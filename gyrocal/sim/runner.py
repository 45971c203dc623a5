"""Run a virtual unit in real time on a transport: pace samples, answer the host, power-cycle.

The sample clock is exact: sample i of a session carries seq i and unit time i / rate_hz, whatever
the wall clock does. Wall time only decides *when* samples go out: every ``batch_s`` (a few ms) the
runner sends all samples due since switch-on, so a 2 kHz unit sends ~8 samples every 4 ms, and a
runner that fell behind catches up in larger batches (at most ``max_batch_s`` worth at once).

Between batches the runner waits on the transport for host requests and answers them at once.
``request_power_cycle``, ``request_stop`` and ``toggle_silence`` only set flags, so they are safe in
signal handlers.

Faults the runner plays (``unit.faults``): a power cycle right after an ack (``cycle_after_ack``),
one sample with a far sequence number every ``seq_outlier_every_s``, and a silence (nothing sent,
nothing answered, the sample counter running on) from ``silence_at_s`` for ``silence_for_s``, or
toggled at run time (SIGUSR2 in ``gyrocal sim``), and samples lost on the link for ``lose_burst_s``
of every ``lose_every_s`` of unit time.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from gyrocal.sim.recorder import Recorder
from gyrocal.sim.unit import VirtualUnit

log = logging.getLogger(__name__)


class Transport(Protocol):
    kind: str
    stats: dict[str, int]

    def describe(self) -> str: ...
    def send(self, msgs: list[Any]) -> None: ...
    def flush(self) -> None: ...
    def poll(self, timeout_s: float) -> list[Any]: ...
    def close(self) -> None: ...

    @property
    def backlog_bytes(self) -> int: ...


def write_json_atomic(path: str | Path, doc: dict[str, Any]) -> None:
    """Write JSON to ``path`` via a temporary file and rename, so a reader never sees half a file."""
    p = Path(path)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    os.replace(tmp, p)


class Runner:
    """Drives ``unit`` on ``transport`` until ``duration_s`` worth of samples is sent (0 = forever).

    ``duration_s`` [s] counts samples, not wall time: the run ends after exactly
    round(duration_s * rate_hz) samples (over all sessions), then serves requests for ``linger_s``
    so the host can read the tail. ``power_cycle_every_s`` [s]: power-cycle after exactly this much
unit time (round(power_cycle_every_s * rate_hz) samples) in each session (0 = never).
    ``status_path``: JSON status, rewritten on every state change and every ``status_every_s``.
    ``flash_path``: the unit's flash (boot counter, applied set) as JSON, written at every switch-on
    and every applied set, as firmware would, so it survives even a SIGKILL of the process.
    """

    def __init__(
        self, unit: VirtualUnit, transport: Transport, *, duration_s: float = 0.0, batch_s: float = 0.004,
        max_batch_s: float = 0.1, status_path: str | Path | None = None, status_every_s: float = 1.0,
        power_cycle_every_s: float = 0.0, recorder: Recorder | None = None, linger_s: float = 0.5,
        info: dict[str, Any] | None = None, flash_path: str | Path | None = None,
    ) -> None:
        self.unit, self.transport = unit, transport
        self.total_samples = round(duration_s * unit.rate_hz) if duration_s > 0 else 0
        self.batch_s, self.max_batch = batch_s, max(1, round(max_batch_s * unit.rate_hz))
        self.status_path, self.status_every_s = status_path, status_every_s
        self.session_samples = round(power_cycle_every_s * unit.rate_hz) if power_cycle_every_s > 0 else 0
        self.recorder, self.linger_s = recorder, linger_s
        self.info = dict(info or {})
        self.flash_path = flash_path
        self._cycle_requested = False
        self._stop_requested = False
        self._silence_toggled = False
        self._replug_requested = False
        self.replugs = 0
        self._started = time.monotonic()
        self._next_outlier = 0
        self.outliers_sent = 0
        self.lost_sent = 0  # samples lost on the link (fault lose_burst_s)
        self._session_t0 = 0.0
        self.replies_sent = 0
        self.requests = 0

    # ---- signal-safe requests ------------------------------------------------------------------
    def request_power_cycle(self) -> None:
        self._cycle_requested = True

    def request_stop(self) -> None:
        self._stop_requested = True

    def request_replug(self) -> None:
        self._replug_requested = True

    def toggle_silence(self) -> None:
        self._silence_toggled = not self._silence_toggled

    def silent(self, now: float) -> bool:
        """True while the unit sends and answers nothing (fault ``silence_*`` or SIGUSR2)."""
        f = self.unit.faults
        t = now - self._started
        window = f.silence_at_s > 0 and f.silence_at_s <= t < f.silence_at_s + f.silence_for_s
        return window != self._silence_toggled

    # ---- the loop ------------------------------------------------------------------------------
    def run(self) -> int:
        """Run until done or stopped; returns 0. Always closes the recorder and writes a final status."""
        try:
            self._power_on()
            next_status = time.monotonic() + self.status_every_s
            while not self._stop_requested:
                now = time.monotonic()
                if self._cycle_requested or (self.session_samples and
                                             self.unit.session_index >= self.session_samples):
                    self._cycle_requested = False
                    self._power_on()
                    continue
                if self._replug_requested and hasattr(self.transport, "reopen"):
                    self._replug_requested = False
                    self.transport.reopen()
                    self.replugs += 1
                    log.info("cable replugged: new port %s", self.transport.describe())
                    self.write_status()
                if self.total_samples and self.unit.samples_sent >= self.total_samples:
                    self._linger()
                    break
                self._send_due(now)
                self._serve(self._session_t0 + self.unit.session_index / self.unit.rate_hz, now)
                if time.monotonic() >= next_status:
                    self.write_status()
                    next_status = time.monotonic() + self.status_every_s
        finally:
            if self.recorder is not None:
                self.recorder.close()
            self.write_status(running=False)
        return 0

    def _power_on(self) -> None:
        hello = self.unit.power_on()
        self.save_flash()
        self._session_t0 = time.monotonic()
        self.transport.send(hello)
        log.info("power on: boot %d", self.unit.boot_count)
        self.write_status()

    def _send_due(self, now: float) -> None:
        due = int((now - self._session_t0) * self.unit.rate_hz) + 1 - self.unit.session_index
        if self.total_samples:
            due = min(due, self.total_samples - self.unit.samples_sent)
        if self.session_samples:
            due = min(due, self.session_samples - self.unit.session_index)
        if due <= 0:
            return
        chunk = self.unit.render(min(due, self.max_batch))
        if self.silent(now):
            return  # the unit's clock and counter run on; nothing reaches the wire
        samples = chunk.samples()
        f = self.unit.faults
        if f.lose_burst_s > 0 and f.lose_every_s > 0:  # lost on the link: seq and time run on
            lost = np.mod(chunk.columns["t"], f.lose_every_s) < f.lose_burst_s
            if lost.any():
                self.lost_sent += int(lost.sum())
                samples = [s for s, gone in zip(samples, lost, strict=True) if not gone]
        every = round(self.unit.faults.seq_outlier_every_s * self.unit.rate_hz)
        if every > 0 and int(chunk.seq[-1]) >= self._next_outlier:
            if self._next_outlier and samples:
                k = len(samples) // 2
                samples[k] = dataclasses.replace(samples[k], seq=(samples[k].seq + 0x40000000) % (1 << 32))
                self.outliers_sent += 1
            self._next_outlier = int(chunk.seq[-1]) + every
        self.transport.send(samples)
        if self.recorder is not None:
            self.recorder.write(chunk.columns)

    def _serve(self, next_sample_at: float, now: float) -> None:
        """Answer host requests until the next batch is due (at least ``batch_s`` from now)."""
        deadline = max(next_sample_at, now + self.batch_s)
        while True:
            timeout = deadline - time.monotonic()
            msgs = self.transport.poll(max(0.0, timeout))
            if msgs and not self.silent(time.monotonic()):
                self._answer(msgs)
            if timeout <= 0 or self._stop_requested or self._cycle_requested:
                return

    def _answer(self, msgs: list[Any]) -> None:
        before = self.unit.applied
        for m in msgs:
            self.requests += 1
            replies = self.unit.handle(m)
            if replies:
                self.transport.send(replies)
                self.replies_sent += len(replies)
        if self.unit.applied is not before:
            log.info("applied coefficient set version %s", self.unit.applied and self.unit.applied.version)
            self.save_flash()
            self.write_status()
        if self.unit.cycle_pending:  # fault: the power fails right after the ack went out
            self.unit.cycle_pending = False
            self.transport.flush()
            self._power_on()

    def _linger(self) -> None:
        end = time.monotonic() + self.linger_s
        while not self._stop_requested and time.monotonic() < end:
            msgs = self.transport.poll(min(0.05, max(0.0, end - time.monotonic())))
            if msgs:
                self._answer(msgs)

    # ---- status --------------------------------------------------------------------------------
    def status(self, running: bool = True) -> dict[str, Any]:
        doc = self.unit.status()
        doc.update(self.info)
        doc.update(running=running, link=self.transport.kind, address=self.transport.describe(),
                   transport=dict(self.transport.stats), backlog_bytes=self.transport.backlog_bytes,
                   requests=self.requests, replies_sent=self.replies_sent, pid=os.getpid(),
                   outliers_sent=self.outliers_sent, lost_on_link=self.lost_sent, replugs=self.replugs,
                   silent=self.silent(time.monotonic()),
                   wall_time=time.time())
        if self.recorder is not None:
            doc.update(record=str(self.recorder.path), recorded_rows=self.recorder.rows)
        return doc

    def save_flash(self) -> None:
        if self.flash_path is None:
            return
        try:
            write_json_atomic(self.flash_path, self.unit.flash_state())
        except OSError as err:
            log.warning("cannot write flash %s: %s", self.flash_path, err)

    def write_status(self, running: bool = True) -> None:
        if self.status_path is None:
            return
        try:
            write_json_atomic(self.status_path, self.status(running))
        except OSError as err:
            log.warning("cannot write status %s: %s", self.status_path, err)
