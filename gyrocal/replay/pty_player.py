"""``gyrocal replay LOG --pty`` / ``--bus``: play a recording in real time, like gpsd's gpsfake.

The recording's samples and HELLOs are written as serial frames into a pty (docs/protocol.md), or
as CAN frames onto a python-can bus, at the pace of their unit time (x ``speed``); a live daemon
opens the pty path printed on the first line of stdout (or ``--pty-link PATH``) as it would a
unit's serial port, or listens on the bus. Unlike ``can.player``, the replayed unit answers: the
host's requests go to the same ReplayUnit as off line (HELLO_REQUEST, COEFF_READ, and COEFF_WRITE
acked and recorded). The
sample stream is cut into ``SLICE_S`` slices, and host frames are read between them, so a push is
answered within a slice and the set it carries compensates the following samples.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from gyrocal.protocol.messages import Sample
from gyrocal.replay.source import Recording
from gyrocal.replay.unit import ReplayUnit
from gyrocal.sim.transports import PtyTransport

SLICE_S = 0.01
"""Samples written per burst [s of unit time]; host requests are read between bursts."""


def _messages(block: np.ndarray) -> list[Sample]:
    return [Sample(int(r["seq"]), float(r["t"]), (float(r["wx"]), float(r["wy"]), float(r["wz"])),
                   (float(r["ax"]), float(r["ay"]), float(r["az"])), float(r["temp"])) for r in block]


def play_pty(recording: Recording, link_path: str | None = None, speed: float = 1.0, linger_s: float = 2.0,
             announce: Callable[[str], None] = print, should_stop: Callable[[], bool] = lambda: False,
             ) -> dict[str, Any]:
    """Play ``recording`` into a new pty; returns what was sent and the pushes recorded."""
    return play(recording, PtyTransport(link_path), speed, linger_s, announce, should_stop)


def play_bus(recording: Recording, bus_kwargs: dict[str, Any], speed: float = 1.0, linger_s: float = 2.0,
             announce: Callable[[str], None] = print, should_stop: Callable[[], bool] = lambda: False,
             dbc_path: str | None = None) -> dict[str, Any]:
    """Play ``recording`` onto a python-can bus (``can.Bus(**bus_kwargs)``) as the unit would send it."""
    from gyrocal.sim.transports import CanTransport

    transport = CanTransport(bus_kwargs, dbc_path=dbc_path)
    return play(recording, transport, speed, linger_s, announce, should_stop)


def play(recording: Recording, pty: Any, speed: float = 1.0, linger_s: float = 2.0,
         announce: Callable[[str], None] = print, should_stop: Callable[[], bool] = lambda: False,
         ) -> dict[str, Any]:
    """Play ``recording`` through a unit-side transport (PtyTransport or CanTransport)."""
    unit = ReplayUnit(recording.first_hello, recording.first_report)
    announce(pty.describe())
    sent = answered = 0
    wall0: float | None = None
    offset, last_t = 0.0, None

    def serve(until_wall: float) -> None:
        nonlocal answered
        while True:
            left = until_wall - time.monotonic()
            for m in pty.poll(max(0.0, left)):
                replies = unit.answer(m)
                answered += len(replies)
                pty.send(replies)
            if left <= 0:
                return

    try:
        for kind, x in recording.events():
            if should_stop():
                break
            if kind == "msg":
                if unit.on_recorded(x):
                    pty.send([x])
                continue
            t = x["t"]
            if last_t is not None and float(t[0]) < last_t:
                offset += last_t + 1.0 - float(t[0])
            dt = float(np.median(np.diff(t))) if t.size > 2 else SLICE_S
            step = max(1, int(round(SLICE_S / dt))) if dt > 0 else 1
            for i in range(0, x.size, step):
                part = x[i:i + step]
                sim = float(part["t"][-1]) + offset
                if wall0 is None:
                    wall0 = time.monotonic() - sim / speed
                serve(wall0 + sim / speed)
                pty.send(_messages(unit.output(part)))
                sent += part.size
            last_t = float(t[-1])
        serve(time.monotonic() + linger_s)  # answer a push or read that came with the last samples
    finally:
        pty.close()
    return {"recording": recording.path, "target": pty.describe(), "samples_sent": sent, "answers": answered,
            "pushes": unit.pushes, "tx": dict(pty.stats)}
