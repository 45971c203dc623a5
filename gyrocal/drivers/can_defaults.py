"""python-can's own configuration sources as the defaults of a gyrocal CAN bus.

Why: a vehicle's CAN set-up is usually configured once, the python-can way: ``/etc/can.conf``,
``~/.canrc`` (or ``~/.can``), and the environment variables ``CAN_INTERFACE``, ``CAN_CHANNEL``,
``CAN_BITRATE`` (can.util.load_config reads them, in that order of precedence after the arguments
given). gyrocal uses the same sources whenever its own configuration (the daemon's ``link.can`` or
``gyrocal sim``'s ``-i/-c/-b``) leaves interface or channel out, so ``can.viewer``, ``can.logger`` and
gyrocal open the same bus.
"""

from __future__ import annotations

from typing import Any

from gyrocal.errors import ConfigError


def with_python_can_defaults(given: dict[str, Any], where: str) -> dict[str, Any]:
    """``given`` completed from python-can's config files and environment.

    Values in ``given`` win. When no source names an interface, ``given`` comes back unchanged (the
    caller decides: the daemon refuses, ``gyrocal sim`` uses udp_multicast). Raises ConfigError naming
    ``where`` for an interface python-can does not know.
    """
    import can
    from can.exceptions import CanInterfaceNotImplementedError

    try:
        return dict(can.util.load_config(config=dict(given)))
    except CanInterfaceNotImplementedError as err:
        if given.get("interface"):
            raise ConfigError(f"{where}: interface {given['interface']!r} is not a python-can interface; "
                              f"write one of {', '.join(sorted(can.VALID_INTERFACES))}") from err
        if "None" in str(err):
            return dict(given)  # no interface anywhere: the caller's default or error
        raise ConfigError(f"{where}: python-can's configuration (CAN_INTERFACE, /etc/can.conf, ~/.canrc) "
                          f"names an unknown interface: {err}") from err
    except (ValueError, OSError) as err:
        raise ConfigError(f"{where}: python-can's configuration could not be read: {err}") from err
