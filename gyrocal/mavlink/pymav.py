"""The one place pymavlink is imported, lazily, so the daemon's core install does not need it.

MAVLink 2 is selected (``MAVLINK20=1`` before the first import): HIGHRES_IMU's ``id`` and
RAW_IMU's ``temperature`` are MAVLink 2 extension fields. The ardupilotmega dialect is a superset of
common.xml, so one dialect decodes both autopilots. ``pip install 'gyrocal[mavlink]'`` provides it.
"""

from __future__ import annotations

import os
from types import ModuleType
from typing import Any

from gyrocal.errors import LinkError

_DIALECT = "ardupilotmega"


def _import() -> tuple[ModuleType, ModuleType]:
    os.environ.setdefault("MAVLINK20", "1")
    try:
        from pymavlink import mavutil
        from pymavlink.dialects.v20 import ardupilotmega as dialect
    except ImportError as err:  # the extra is not installed
        raise LinkError(
            "the mavlink link needs pymavlink; install it with pip install 'gyrocal[mavlink]'"
        ) from err
    return mavutil, dialect


def mavutil() -> ModuleType:
    """pymavlink.mavutil, with MAVLink 2 selected."""
    return _import()[0]


def dialect() -> ModuleType:
    """The generated MAVLink 2 ardupilotmega module (message classes and enums)."""
    return _import()[1]


def codec(src_system: int, src_component: int) -> Any:
    """A bare ``MAVLink`` encoder/decoder (no file): ``.x_encode(...).pack(codec)``, ``parse_buffer``."""
    mav = dialect().MAVLink(None, srcSystem=src_system, srcComponent=src_component)
    mav.robust_parsing = True
    return mav
