"""The CAN link: any python-can interface (socketcan, virtual, udp_multicast, pcan, ...).

The bus is opened with ``can.Bus(**bus_kwargs)``, so a config names any interface python-can knows.
The reader thread calls ``bus.recv(poll_s)``, then drains what is already queued, and feeds each
frame to the protocol's ``CanDecoder``, which reassembles samples and coefficient reports.

Node: a unit has a node id 0..15 (docs/protocol.md, "CAN node id"); the link talks to one node,
``node_id`` (config ``link.can_node_id``), and its frame ids are the DBC's node-0 ids plus node_id.

Direction: only frames the DBC marks as sent by the UNIT (of this node) are decoded. ``udp_multicast``
loops a sender's own datagrams back to it (its ``receive_own_messages=False`` does not filter them),
so the host would otherwise read its own COEFF_* frames: those are counted as ``echo_frames``. Every
other frame (another node's, another protocol's) goes to the decoder, which counts it in
``foreign_frames`` (or ``unknown_types`` for an unknown function code on this node's ids).

Another host: a host-to-unit frame (COEFF_*, COEFF_READ, HELLO_REQUEST on this node) that this link
did not send, or sent more times than it comes back, is another host's: counted in
``other_host_frames``, with one WARNING a minute while they come. Two calibrators on one bus mint the
same version numbers for different sets and overwrite each other's pushes (an integrator's fault
campaign: the unit held daemon 1's v2 while daemon 2's store recorded its own v2 as acked); the
daemon cannot stop the other one, so it says so.

Reconnect: ``can.CanError`` or ``OSError`` from ``recv`` (an interface that went down, a USB adapter
unplugged) shuts the bus down and reopens it with backoff.
"""

from __future__ import annotations

import collections
import logging
import os
import socket
import threading
import time
from typing import Any

import can

from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers.base import ControlCallback, EventCallback, Link
from gyrocal.errors import ConfigError, LinkError

log = logging.getLogger(__name__)

DRAIN_MAX = 4096
"""Frames read per wake-up before the reader yields (bounds one batch's latency)."""
SENT_KEPT = 512
"""Own host-to-unit frames remembered to recognise their echo (a push is at most ~130 frames)."""
OTHER_HOST_SAY_S = 60.0
"""At most one WARNING per this many seconds [s] about another host's frames."""


def check_bus_kwargs(bus_kwargs: dict[str, Any]) -> dict[str, Any]:
    """Validate ``can.Bus`` arguments without opening the bus; ConfigError names the field and a fix."""
    if not isinstance(bus_kwargs, dict):
        raise ConfigError(f"CAN bus config must be a mapping of can.Bus arguments, got {bus_kwargs!r}")
    iface = bus_kwargs.get("interface", bus_kwargs.get("bustype"))
    if not iface:
        raise ConfigError('CAN bus config: field "interface" missing; '
                          "e.g. socketcan, virtual or udp_multicast")
    if iface not in can.interfaces.VALID_INTERFACES:
        known = ", ".join(sorted(can.interfaces.VALID_INTERFACES))
        raise ConfigError(f"CAN bus config: interface {iface!r} is not a python-can interface; "
                          f"pick one of {known}")
    return dict(bus_kwargs)


def frame_ids_sent_by(codec: Any, node: str) -> frozenset[int] | None:
    """Arbitration ids the DBC says ``node`` (UNIT or HOST) sends; None (accept all) if it does not say."""
    try:
        ids = {codec.ids[m.name] for m in codec.db.messages if node in (m.senders or [])}
    except (AttributeError, KeyError):
        return None
    return frozenset(ids) or None


class CanLink(Link):
    """A link over a python-can bus. ``bus_kwargs`` go to ``can.Bus`` unchanged.

    ``dbc_path``: the CAN database (default: the shipped configs/gyrocal.dbc).
    """

    kind = "can"
    _io_errors = (OSError, can.CanError)

    def __init__(
        self, bus_kwargs: dict[str, Any], ring: RingBuffer, on_control: ControlCallback,
        on_event: EventCallback | None = None, *, dbc_path: str | None = None, node_id: int = 0,
        **link_kwargs: Any,
    ) -> None:
        super().__init__(ring, on_control, on_event, **link_kwargs)
        from gyrocal.protocol.can_codec import CanCodec

        self.bus_kwargs = check_bus_kwargs(bus_kwargs)
        self._codec = CanCodec(dbc_path, node_id=node_id)
        self._decoder = self._codec.decoder()
        self._accept = frame_ids_sent_by(self._codec, "UNIT")
        self._echo_ids = frame_ids_sent_by(self._codec, "HOST") or frozenset()
        self._bus: can.BusABC | None = None
        self._own_echo = 0
        self._sent: collections.Counter[tuple[int, bytes]] = collections.Counter()  # not yet echoed
        self._sent_order: collections.deque[tuple[int, bytes]] = collections.deque()
        self._sent_lock = threading.Lock()
        self.other_host_frames = 0
        self._other_said_at = -float("inf")

    @property
    def target(self) -> str:
        return "can.Bus(" + ", ".join(f"{k}={v!r}" for k, v in self.bus_kwargs.items()) + ")"

    def _open(self) -> None:
        try:
            bus = can.Bus(**self.bus_kwargs)
        except (can.CanError, OSError, ValueError, TypeError, ImportError) as err:
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise LinkError(f"CAN bus {self.target} cannot be opened ({reason}); check the interface is up "
                            "(ip link show) and the channel name") from err
        enlarge_receive_buffer(bus)
        self._bus = bus
        self._decoder.reset()  # parts of a sample or transfer cut by the last outage are not resumed

    def _close(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def _receive(self) -> list[Any]:
        bus = self._bus
        if bus is None:
            raise OSError("bus closed")
        frame = bus.recv(self.poll_s)
        out: list[Any] = []
        accept, echo, feed = self._accept, self._echo_ids, self._decoder.feed
        budget = DRAIN_MAX
        while frame is not None:
            if accept is not None and frame.arbitration_id in echo:
                self._host_frame(frame)  # our own COEFF_* frames looped back, or another host's
            else:
                out.extend(feed(frame))  # the unit's, or foreign (the decoder counts those)
            budget -= 1
            if budget <= 0:
                break
            frame = bus.recv(0.0)
        return out

    def _host_frame(self, frame: can.Message) -> None:
        key = (frame.arbitration_id, bytes(frame.data))
        with self._sent_lock:
            own = self._sent[key] > 0
            if own:
                self._sent[key] -= 1
                # its send leaves the window too: left there, trimming it later took the count of a
                # newer identical frame (a write resent on BUSY), whose echo was then called another
                # host's (an integrator's campaign: at the 6th write of one version, 3 runs of 3)
                self._sent_order.remove(key)
        if own:
            self._own_echo += 1
            return
        self.other_host_frames += 1
        now = time.monotonic()
        if now - self._other_said_at >= OTHER_HOST_SAY_S:
            self._other_said_at = now
            log.warning("CAN node %d: %d host-to-unit frame(s) this daemon did not send (0x%03X ...): "
                        "another host is talking to the unit; two calibrators on one bus overwrite each "
                        "other's sets and versions (link.other_host_frames)", self._codec.node_id,
                        self.other_host_frames, frame.arbitration_id)

    def _transmit(self, msg: Any) -> None:
        bus = self._bus
        if bus is None:
            raise OSError("bus closed")
        for frame in self._codec.encode(msg):
            key = (frame.arbitration_id, bytes(frame.data))
            with self._sent_lock:  # what may come back as our own echo (bounded: the last SENT_KEPT)
                self._sent[key] += 1
                self._sent_order.append(key)
                while len(self._sent_order) > SENT_KEPT:
                    old = self._sent_order.popleft()
                    if self._sent[old] > 0:
                        self._sent[old] -= 1
                    if self._sent[old] <= 0:
                        del self._sent[old]
            bus.send(frame, timeout=1.0)

    def _decoder_stats(self) -> dict[str, int]:
        return self._decoder.stats.as_dict()

    def _transport_stats(self) -> dict[str, int]:
        return {"echo_frames": self._own_echo, "other_host_frames": self.other_host_frames}


def enlarge_receive_buffer(bus: can.BusABC, size_bytes: int = 4 << 20) -> None:
    """Ask for a larger kernel receive buffer on a socket-based bus (udp_multicast, socketcan).

    A UDP socket's default buffer holds only ~256 datagrams: a reader that stalls for 40 ms at 6000
    frames/s would drop frames. The kernel caps the size at net.core.rmem_max. Best effort: works on
    a duplicate of the bus's descriptor, so only public python-can API is used.
    """
    try:
        fd = bus.fileno()
    except (NotImplementedError, AttributeError, OSError):
        return
    if not isinstance(fd, int) or fd < 0:
        return
    dup = os.dup(fd)
    try:
        s = socket.socket(fileno=dup)
    except OSError:  # not a socket
        os.close(dup)
        return
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size_bytes)
    except OSError:
        log.debug("could not enlarge the receive buffer of %s", bus, exc_info=True)
    finally:
        s.close()
