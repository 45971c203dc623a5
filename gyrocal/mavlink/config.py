"""The ``link: {kind: mavlink, ...}`` config fields, checked with messages that name the fix.

    link: {kind: mavlink, url: /dev/ttyACM0, baudrate: 921600, autopilot: px4}
    link: {kind: mavlink, url: "udpin:0.0.0.0:14550", autopilot: ardupilot,
           state_file: /var/lib/gyrocal/mav.json}

``url`` is a pymavlink connection string (a serial device, ``udp:``/``udpin:``, ``udpout:``, ``tcp:``).
Optional: ``autopilot`` (px4 | ardupilot; default: from the heartbeat), ``instance`` (IMU 0..2),
``rate_hz`` (IMU stream, default 250), ``state_file``, ``tmin_c``/``tmax_c`` (fix TMIN/TMAX instead
of the range seen), ``heartbeat_timeout_s``, ``param_timeout_s``, ``param_retries``.
"""

from __future__ import annotations

from typing import Any

from gyrocal.errors import ConfigError

FIELDS = (
    "url",
    "baudrate",
    "autopilot",
    "instance",
    "rate_hz",
    "state_file",
    "tmin_c",
    "tmax_c",
    "heartbeat_timeout_s",
    "param_timeout_s",
    "param_retries",
    "source_system",
)


def mavlink_link(
    where: str, rest: dict[str, Any], ring: Any, on_control: Any, on_event: Any, common: dict[str, float]
) -> Any:
    unknown = sorted(set(rest) - set(FIELDS))
    if unknown:
        raise ConfigError(
            f"{where}: unknown field {unknown[0]!r} for a mavlink link; known: {', '.join(FIELDS)}"
        )
    url = rest.get("url")
    if not isinstance(url, str) or not url:
        raise ConfigError(
            f"{where}: field 'url' missing; give a serial device (/dev/ttyACM0) or "
            "udpin:0.0.0.0:14550 / udpout:HOST:PORT / tcp:HOST:PORT"
        )
    kw: dict[str, Any] = {}
    if "autopilot" in rest:
        if rest["autopilot"] not in ("px4", "ardupilot"):
            raise ConfigError(f"{where}: field 'autopilot' is {rest['autopilot']!r}; write px4 or ardupilot")
        kw["autopilot"] = rest["autopilot"]
    for name, lo, hi in (
        ("baudrate", 1, 10_000_000),
        ("instance", 0, 2),
        ("param_retries", 1, 20),
        ("source_system", 1, 255),
    ):
        if name in rest:
            v = rest[name]
            if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
                raise ConfigError(f"{where}: field '{name}' must be an integer in {lo}..{hi}, got {v!r}")
            kw[name] = v
    for name in ("rate_hz", "heartbeat_timeout_s", "param_timeout_s", "tmin_c", "tmax_c"):
        if name in rest:
            v = rest[name]
            positive = name not in ("tmin_c", "tmax_c")  # temperatures [degC] may be negative
            if not isinstance(v, int | float) or isinstance(v, bool) or (positive and v <= 0):
                need = "a number > 0" if positive else "a temperature in degC"
                raise ConfigError(f"{where}: field '{name}' must be {need}, got {v!r}")
            kw[name] = float(v)
    if "state_file" in rest:
        if not isinstance(rest["state_file"], str):
            raise ConfigError(f"{where}: field 'state_file' must be a file path")
        kw["state_file"] = rest["state_file"]
    from gyrocal.mavlink.link import MavlinkLink

    return MavlinkLink(url, ring, on_control, on_event, **kw, **common)
