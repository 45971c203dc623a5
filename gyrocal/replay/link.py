"""The replay Link (link kind ``replay``): a recording fed through the daemon's ring and inbox.

It is a ``drivers.base.Link`` like the serial and CAN links, so the engine cannot tell it apart:
samples go into the ring, the unit's other messages to ``on_control`` in stream order, and
``send`` reaches a unit, the ReplayUnit, which answers from the recording.

Two ways to run:

- off line (``gyrocal replay``): no reader thread. The caller ``pump()``s one chunk at a time and
  the shared ``SimClock`` reads the recording's unit time, so the engine's timeouts, still
  detector and validation run on recorded time, at full speed, the same way every run;
- live (``open_link({"kind": "replay", "path": ...})`` in a daemon config): the reader thread plays
  the recording at its own pace (``speed`` x real time).

A chunk ends at ``chunk_s`` of unit time (at least 64 samples, so the engine loop never sleeps on a
short block, and at most 8192, what the engine pops in one round) or at a unit message, so every
message reaches the engine after exactly the samples that preceded it in the recording.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers.base import ControlCallback, EventCallback, Link
from gyrocal.errors import ConfigError
from gyrocal.protocol.messages import Sample
from gyrocal.replay.source import Event, Recording, open_recording
from gyrocal.replay.unit import ReplayUnit

MIN_CHUNK, MAX_CHUNK = 64, 8192
SESSION_GAP_S = 1.0
"""Simulated time inserted where the unit's clock restarts (a power cycle), so the clock never goes back."""


class SimClock:
    """A monotonic clock [s] that the replay sets: the recording's unit time, made monotonic."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class ReplayLink(Link):
    """A link whose far end is a recording. ``clock``: a SimClock for off-line mode, None for live."""

    kind = "replay"

    def __init__(
        self, recording: Recording, ring: RingBuffer, on_control: ControlCallback,
        on_event: EventCallback | None = None, *, clock: SimClock | None = None, chunk_s: float = 0.25,
        speed: float = 1.0, **link_kwargs: Any,
    ) -> None:
        super().__init__(ring, on_control, on_event, **link_kwargs)
        self.recording = recording
        self.clock = clock
        self.chunk_s = chunk_s
        self.speed = speed
        self.unit = ReplayUnit(recording.first_hello, recording.first_report)
        self.exhausted = False
        self._events: Iterator[Event] | None = None
        self._pending: Event | None = None
        self._chunk_n = MIN_CHUNK
        self._offset = 0.0  # clock = unit time + offset
        self._last_t: float | None = None
        self._frames = 0
        self._wall0: float | None = None
        self._sim0 = 0.0

    @property
    def target(self) -> str:
        return f"recording {self.recording.path}"

    # -- Link hooks ----------------------------------------------------------------------------
    def _open(self) -> None:
        if self._events is None:
            self._events = self.recording.events()

    def _close(self) -> None:
        pass

    def start(self, wait: bool = True) -> None:
        """Off line: open without a reader thread (the caller pumps). Live: the base class's thread."""
        if self.clock is None:
            super().start(wait)
            return
        self._open()
        self._set_up()

    def _transmit(self, msg: Any) -> None:
        for reply in self.unit.answer(msg):
            self._frames += 1
            self.on_control(reply)

    def _decoder_stats(self) -> dict[str, int]:
        return {"frames": self._frames, **self.recording.dropped()}

    def _receive(self) -> list[Any]:
        """Live mode: the next chunk as messages, once its unit time is due on the wall clock."""
        if self.exhausted:
            time.sleep(self.poll_s)
            return []
        chunk = self._chunk()
        if not chunk:
            return []
        sim = (self._last_t or 0.0) + self._offset
        if self._wall0 is None:
            self._wall0, self._sim0 = time.monotonic(), sim
        wait = self._wall0 + (sim - self._sim0) / self.speed - time.monotonic()
        if wait > 0:
            self._stop_evt.wait(wait)
        out: list[Any] = []
        for kind, x in chunk:
            if kind == "msg":
                out.append(x)
                continue
            out.extend(Sample(int(r["seq"]), float(r["t"]), (float(r["wx"]), float(r["wy"]), float(r["wz"])),
                              (float(r["ax"]), float(r["ay"]), float(r["az"])), float(r["temp"])) for r in x)
        return out

    # -- off line ------------------------------------------------------------------------------
    def pump(self) -> bool:
        """Feed the next chunk into the ring (and its message into the inbox); False when done."""
        fed = False
        for kind, x in self._chunk():
            fed = True
            if kind == "msg":
                self._frames += 1
                self.on_control(x)
            else:
                self.ring.push_block(x)
                self._counts["samples"] += int(x.size)
        return fed

    def _chunk(self) -> list[Event]:
        """The next chunk: samples up to chunk_s (re-compensated, timed) or up to and with one message."""
        out: list[Event] = []
        budget = self._chunk_n
        while budget > 0:
            ev = self._next()
            if ev is None:
                self.exhausted = True
                break
            kind, x = ev
            if kind == "msg":
                if self.unit.on_recorded(x):
                    self._counts["control"] += 1
                    out.append(ev)
                    break
                continue
            if x.size > budget:
                self._pending = ("samples", x[budget:])
                x = x[:budget]
            out.append(("samples", self._timed(x)))
            budget -= x.size
        return out

    def _next(self) -> Event | None:
        if self._pending is not None:
            ev, self._pending = self._pending, None
            return ev
        if self._events is None:
            self._open()
        return next(self._events, None)  # type: ignore[arg-type]

    def _timed(self, block: np.ndarray) -> np.ndarray:
        """Set the clock from the block's unit time (monotonic across restarts); re-compensate it."""
        t = block["t"]
        if self._last_t is None and block.size > 2:
            dt = float(np.median(np.diff(t)))
            if dt > 0:
                self._chunk_n = int(min(MAX_CHUNK, max(MIN_CHUNK, round(self.chunk_s / dt))))
        if self._last_t is not None and float(t[0]) < self._last_t:
            self._offset = self._last_t + self._offset + SESSION_GAP_S - float(t[0])
        self._last_t = float(t[-1])
        out = self.unit.output(block)
        if self.clock is not None:
            self.clock.now = self._last_t + self._offset
            out["rx"] = self.clock.now
        return out


def from_config(where: str, rest: dict[str, Any], ring: RingBuffer, on_control: ControlCallback,
                on_event: EventCallback | None, common: dict[str, float]) -> ReplayLink:
    """``{"kind": "replay", "path": LOG, "speed": 1.0, "format": null}`` for ``drivers.open_link``."""
    path = rest.pop("path", None)
    if not isinstance(path, str) or not path:
        raise ConfigError(f"{where}: field 'path' missing; name the recording to replay")
    speed = rest.pop("speed", 1.0)
    if not isinstance(speed, int | float) or isinstance(speed, bool) or speed <= 0:
        raise ConfigError(f"{where}: field 'speed' must be a number > 0 (1 = real time), got {speed!r}")
    fmt = rest.pop("format", None)
    if rest:
        raise ConfigError(f"{where}: unknown field {sorted(rest)[0]!r} for a replay link; "
                          "known: path, speed, format")
    return ReplayLink(open_recording(path, fmt), ring, on_control, on_event, clock=None, speed=float(speed),
                      **common)
