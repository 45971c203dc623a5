"""Links to the strapdown unit: serial (any pyserial URL) and CAN (any python-can interface).

``open_link(cfg, ...)`` builds one from a config mapping, found by name in ``LINKS`` and imported
lazily (as python-can finds interfaces), so a serial-only daemon never imports python-can::

    {"kind": "serial", "url": "/dev/ttyUSB0", "baudrate": 921600}
    {"kind": "can", "bus": {"interface": "socketcan", "channel": "can0"}}
    {"kind": "can", "interface": "udp_multicast", "channel": "239.74.163.2", "port": 43113}

Optional in both: ``backoff_initial_s``, ``backoff_max_s``, ``poll_s`` [s]; CAN also ``dbc`` (path).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from gyrocal.errors import ConfigError

if TYPE_CHECKING:
    from gyrocal.daemon.ring import RingBuffer
    from gyrocal.drivers.base import ControlCallback, EventCallback, Link
    from gyrocal.drivers.can_link import CanLink
    from gyrocal.drivers.serial_link import SerialLink

LINKS: dict[str, tuple[str, str]] = {
    "serial": ("gyrocal.drivers.serial_link", "SerialLink"),
    "can": ("gyrocal.drivers.can_link", "CanLink"),
    "mavlink": ("gyrocal.mavlink.link", "MavlinkLink"),
    "replay": ("gyrocal.replay.link", "ReplayLink"),
}
"""Link kinds -> (module, class), imported on first use."""

_COMMON = ("backoff_initial_s", "backoff_max_s", "poll_s")
_SERIAL = ("url", "port", "baudrate", "write_timeout_s")

__all__ = ["LINKS", "CanLink", "SerialLink", "link_class", "open_link"]


def link_class(kind: str) -> type[Link]:
    """The Link subclass registered under ``kind``."""
    module, name = LINKS[kind]
    return getattr(importlib.import_module(module), name)


def __getattr__(name: str) -> Any:  # lazy ``from gyrocal.drivers import SerialLink``
    for kind, (_, cls) in LINKS.items():
        if cls == name:
            return link_class(kind)
    raise AttributeError(name)


def open_link(
    cfg: Mapping[str, Any], ring: RingBuffer, on_control: ControlCallback,
    on_event: EventCallback | None = None, *, start: bool = True, wait: bool = True, where: str = "link",
) -> Link:
    """Build a link from ``cfg`` and (by default) start it.

    Raises ``ConfigError`` for a malformed config (``where`` names it in the message, e.g.
    "gyrocal.yaml: link"). With ``wait=True`` an unknown port or a bus that cannot open raises
    ``LinkError`` at once; with ``wait=False`` the reader thread keeps retrying with backoff and
    reports ``reconnecting`` events (a daemon that starts before its unit is plugged in).
    """
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"{where}: must be a mapping with a 'kind' field (serial or can)")
    kind = cfg.get("kind", cfg.get("type"))
    if kind not in LINKS:
        raise ConfigError(f"{where}: field 'kind' is {kind!r}; write one of {', '.join(LINKS)}")
    rest = {k: v for k, v in cfg.items() if k not in ("kind", "type")}
    common = {k: _seconds(where, k, rest.pop(k)) for k in _COMMON if k in rest}
    link: Link
    if kind == "serial":
        link = _serial(where, rest, ring, on_control, on_event, common)
    elif kind == "mavlink":
        from gyrocal.mavlink.config import mavlink_link

        link = mavlink_link(where, rest, ring, on_control, on_event, common)
    elif kind == "replay":  # a recording played as the unit (gyrocal/replay/link.py)
        from gyrocal.replay.link import from_config

        link = from_config(where, rest, ring, on_control, on_event, common)
    else:
        link = _can(where, rest, ring, on_control, on_event, common)
    if start:
        link.start(wait=wait)
    return link


def _seconds(where: str, field: str, value: Any) -> float:
    if not isinstance(value, int | float) or isinstance(value, bool) or value <= 0:
        raise ConfigError(f"{where}: field '{field}' must be a number of seconds > 0, got {value!r}")
    return float(value)


def _serial(where: str, rest: dict[str, Any], ring: Any, on_control: Any, on_event: Any,
            common: dict[str, float]) -> Link:
    unknown = sorted(set(rest) - set(_SERIAL))
    if unknown:
        raise ConfigError(f"{where}: unknown field {unknown[0]!r} for a serial link; "
                          f"known: {', '.join(_SERIAL)}")
    url = rest.get("url", rest.get("port"))
    if not isinstance(url, str) or not url:
        raise ConfigError(f"{where}: field 'url' missing; give a device path (/dev/ttyUSB0) or pyserial URL")
    from gyrocal.drivers.serial_link import DEFAULT_BAUDRATE, SerialLink

    baud = rest.get("baudrate", DEFAULT_BAUDRATE)
    if not isinstance(baud, int) or isinstance(baud, bool) or baud <= 0:
        raise ConfigError(f"{where}: field 'baudrate' must be a positive integer (bit/s), got {baud!r}")
    extra = {"write_timeout_s": _seconds(where, "write_timeout_s", rest["write_timeout_s"])} \
        if "write_timeout_s" in rest else {}
    return SerialLink(url, ring, on_control, on_event, baudrate=baud, **extra, **common)


def _can(where: str, rest: dict[str, Any], ring: Any, on_control: Any, on_event: Any,
         common: dict[str, float]) -> Link:
    from gyrocal.drivers.can_link import CanLink, check_bus_kwargs

    dbc = rest.pop("dbc", None)
    if dbc is not None and not isinstance(dbc, str):
        raise ConfigError(f"{where}: field 'dbc' must be a file path")
    node_id = rest.pop("node_id", 0)
    if not isinstance(node_id, int) or isinstance(node_id, bool) or not 0 <= node_id <= 15:
        raise ConfigError(f"{where}: field 'node_id' is {node_id!r}; write the unit's CAN node id, 0 to 15")
    bus = rest.pop("bus", None)
    if bus is None:
        bus = rest
    elif rest:
        raise ConfigError(f"{where}: unknown field {sorted(rest)[0]!r}; put can.Bus arguments under 'bus'")
    try:
        kwargs = check_bus_kwargs(dict(bus) if isinstance(bus, Mapping) else bus)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from err
    return CanLink(kwargs, ring, on_control, on_event, dbc_path=dbc, node_id=node_id, **common)
