"""The shared machinery of every link to the unit: reader thread, reconnect, dispatch, statistics.

Modelled on python-can's ``BusABC`` and pyserial's ``ReaderThread``: the base class owns the public
edges (``start``, ``stop``, ``send``, ``stats``, reconnect with backoff, the context manager), and a
transport implements only a narrow set of hooks:

- ``_open()``: open the device; raise ``LinkError`` (one line naming the target and a fix);
- ``_close()``: release it, never raising;
- ``_receive()``: wait up to ``poll_s`` for input and return decoded messages; raise ``OSError``
  (or the transport's I/O error, listed in ``_io_errors``) when the device is gone;
- ``_transmit(msg)``: encode and write one message (called under the write lock);
- ``_decoder_stats()``: the protocol decoder's counters.

Threads: one reader thread owns all input. ``send`` may be called from any thread and writes under
a lock. Samples go into the ring (this thread is its single producer); every other message goes to
``on_control(msg)``, called on the reader thread in stream order, so ``ring.pushed`` read inside
``on_control`` marks exactly where that message fell in the sample stream (e.g. a HELLO's session
boundary). Callbacks must be quick. An exception in a callback is logged and counted
(``callback_errors``) apart from I/O errors; it never stops the reader.

Events, via ``on_event(name, detail)``: ``link_up``, ``link_lost``, ``reconnecting``.
"""

from __future__ import annotations

import logging
import threading
import time
import warnings
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

from gyrocal.daemon.ring import RingBuffer
from gyrocal.errors import LinkError
from gyrocal.protocol.messages import Sample

log = logging.getLogger(__name__)

ControlCallback = Callable[[Any], None]
EventCallback = Callable[[str, str], None]


class Link(ABC):
    """A link to one unit. Subclasses: ``SerialLink``, ``CanLink``.

    ``backoff_initial_s`` / ``backoff_max_s`` [s]: reconnect delays, doubling from the first to the
    cap. ``poll_s`` [s]: how long one ``_receive`` may block, which bounds how fast ``stop`` returns.
    """

    kind = "link"
    _io_errors: tuple[type[BaseException], ...] = (OSError,)

    def __init__(
        self, ring: RingBuffer, on_control: ControlCallback, on_event: EventCallback | None = None,
        *, backoff_initial_s: float = 0.1, backoff_max_s: float = 5.0, poll_s: float = 0.05,
    ) -> None:
        self.ring = ring
        self.on_control = on_control
        self.on_event = on_event
        self.backoff_initial_s, self.backoff_max_s, self.poll_s = backoff_initial_s, backoff_max_s, poll_s
        self._write_lock = threading.Lock()
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected = False
        self._ever_up = False
        self._stopped = False
        self._counts = {"samples": 0, "control": 0, "messages_sent": 0, "io_errors": 0,
                        "callback_errors": 0, "send_errors": 0, "reconnects": 0}

    # ---- hooks ---------------------------------------------------------------------------------
    @property
    @abstractmethod
    def target(self) -> str:
        """What this link talks to, for messages (a port path, URL or bus description)."""

    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _close(self) -> None: ...

    @abstractmethod
    def _receive(self) -> list[Any]: ...

    @abstractmethod
    def _transmit(self, msg: Any) -> None: ...

    @abstractmethod
    def _decoder_stats(self) -> dict[str, int]: ...

    def _transport_stats(self) -> dict[str, int]:
        return {}

    # ---- public API ----------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """True while the device is open and reading."""
        return self._connected

    def start(self, wait: bool = True) -> None:
        """Start the reader thread.

        ``wait=True`` opens the device first, in the caller, and raises ``LinkError`` when it cannot
        (a config that names an unknown port fails at once). ``wait=False`` returns at once and the
        reader thread keeps trying with backoff (a daemon that must outlive an unplugged unit).
        """
        if self._thread is not None:
            return
        if self._stopped:
            raise LinkError(f"{self.kind} link to {self.target} was stopped; create a new link to restart")
        if wait:
            self._open()
            self._set_up()
        self._thread = threading.Thread(target=self._run, name=f"gyrocal-{self.kind}-reader", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the reader thread and close the device. Idempotent; safe from any thread."""
        self._stopped = True
        self._stop_evt.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout_s)
        self._connected = False
        self._close_quietly()

    def send(self, msg: Any) -> None:
        """Encode and write one message to the unit. Raises ``LinkError`` when the link is down."""
        if not self._connected:
            raise LinkError(f"{self.kind} link to {self.target} is down; the message was not sent")
        try:
            with self._write_lock:
                self._transmit(msg)
            self._counts["messages_sent"] += 1
        except self._io_errors as err:
            self._counts["send_errors"] += 1
            raise LinkError(f"{self.kind} link to {self.target}: write failed ({err})") from err

    def stats(self) -> dict[str, Any]:
        """Counters: frames, bytes, errors per kind, ring drops, reconnects (a fresh dict)."""
        dec = self._decoder_stats()
        c = dict(self._counts)
        errors = {k: v for k, v in dec.items() if k not in ("frames", "bytes")}
        errors.update(io_errors=c.pop("io_errors"), callback_errors=c.pop("callback_errors"),
                      send_errors=c.pop("send_errors"))
        out: dict[str, Any] = {"kind": self.kind, "target": self.target, "connected": self._connected,
                               "frames": dec.get("frames", 0), "bytes": dec.get("bytes", 0), **c,
                               "errors": errors, "drops": self.ring.lost}
        out.update(self._transport_stats())
        return out

    def __enter__(self) -> Link:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def __del__(self) -> None:
        if getattr(self, "_thread", None) is not None and not getattr(self, "_stopped", True):
            warnings.warn(f"{self.kind} link to {self.target} was not stopped", ResourceWarning, stacklevel=2)

    # ---- the reader thread ---------------------------------------------------------------------
    def _run(self) -> None:
        delay = self.backoff_initial_s
        while not self._stop_evt.is_set():
            if not self._connected:
                try:
                    self._open()
                except Exception as err:  # LinkError and I/O errors; anything else is retried too
                    if not isinstance(err, (LinkError, *self._io_errors)):
                        log.exception("%s link: unexpected error opening %s", self.kind, self.target)
                    self._emit("reconnecting", f"{err}; next try in {delay:.1f} s")
                    self._stop_evt.wait(delay)
                    delay = min(delay * 2.0, self.backoff_max_s)
                    continue
                delay = self.backoff_initial_s
                self._set_up()
            try:
                msgs = self._receive()
            except Exception as err:  # the device vanished (or a transport bug): close and reopen
                if not isinstance(err, self._io_errors):
                    log.exception("%s link: unexpected error reading %s", self.kind, self.target)
                self._counts["io_errors"] += 1
                self._connected = False
                self._close_quietly()
                if not self._stop_evt.is_set():
                    self._emit("link_lost", f"{self.target}: {err}")
                    self._stop_evt.wait(self.backoff_initial_s)  # a flapping device cannot spin us
                continue
            if msgs:
                self._dispatch(msgs)
        self._connected = False
        self._close_quietly()

    def _set_up(self) -> None:
        if self._ever_up:
            self._counts["reconnects"] += 1
        self._ever_up = True
        self._connected = True
        self._emit("link_up", self.target)

    def _dispatch(self, msgs: list[Any]) -> None:
        rx = time.monotonic()
        ring, counts = self.ring, self._counts
        for m in msgs:
            try:
                if type(m) is Sample:
                    ring.push(m, rx)
                    counts["samples"] += 1
                else:
                    counts["control"] += 1
                    self.on_control(m)
            except Exception:  # a callback's bug must not stop the reader
                counts["callback_errors"] += 1
                if counts["callback_errors"] <= 10 or counts["callback_errors"] % 1000 == 0:
                    log.exception("%s link: callback failed on %s", self.kind, type(m).__name__)

    def _emit(self, name: str, detail: str) -> None:
        # every back-off round would be a line, and the listener (the engine) logs each event once
        # itself: with a listener, the driver's own line is DEBUG (one unplug gave four lines)
        level = logging.DEBUG if name == "reconnecting" or self.on_event is not None else logging.INFO
        log.log(level, "%s link %s: %s", self.kind, name, detail)
        if self.on_event is None:
            return
        try:
            self.on_event(name, detail)
        except Exception:
            self._counts["callback_errors"] += 1
            log.exception("%s link: on_event(%s) failed", self.kind, name)

    def _close_quietly(self) -> None:
        try:
            with self._write_lock:
                self._close()
        except Exception:  # closing a vanished device may fail; nothing to do about it
            log.debug("%s link: close failed", self.kind, exc_info=True)
