"""What the MAVLink link must remember across daemon restarts, in one small JSON file.

Neither autopilot has a parameter we may use for our calibration version (PX4's TC_G* and
ArduPilot's INS_TCAL* are all coefficients), so the version lives here, with the exact parameter
values of the set it names. A read whose durable parameters equal the stored ones is that version;
anything else (a set from process_sensor_caldata.py, an ArduPilot learning run, a hand edit) is
reported as version 0: the coefficients are still read from the unit, never assumed.

Per unit (by the serial the link derives): ``boot_count`` and ``boot_wall`` (wall-clock time of the
last boot seen: uptime subtracted from time.time(), so a restarted daemon does not count the same
boot twice), the pushed set (``version``, ``coeffs``, ``durable``, ``target``), and the temperature
range seen over all boots (``temp_range``), from which TMIN/TMAX are taken. Writes are atomic
(tmp + rename): a crash leaves the old file or the new one.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

log = logging.getLogger("gyrocal.mavlink.state")


KEPT_RANGES = 50
"""Versions whose temperature range [degC] the state file keeps (``keep_range``)."""


class LinkState:
    """``path=None`` keeps the state in memory only (versions then read as 0 after a restart)."""

    def __init__(self, path: str | Path | None) -> None:
        self.path = Path(path) if path else None
        self.units: dict[str, dict[str, Any]] = {}
        if self.path is not None and self.path.exists():
            try:
                doc = json.loads(self.path.read_text(encoding="utf-8"))
                self.units = dict(doc.get("units", {}))
            except (OSError, ValueError, AttributeError) as err:
                log.error(
                    "mavlink state %s unreadable (%s); starting afresh, versions read as 0", self.path, err
                )
                self.units = {}

    def unit(self, serial: int) -> dict[str, Any]:
        return self.units.setdefault(str(serial), {})

    def note_boot(
        self, serial: int, boot_wall: float, *, known_new: bool = False, tolerance_s: float = 5.0
    ) -> int:
        """The boot count for a boot at ``boot_wall`` [s since epoch]; +1 when it is a new boot.

        ``known_new``: the link saw the reboot itself (time went back, heartbeat returned). Otherwise
        (the first contact after the link started) a boot more than ``tolerance_s`` away from the
        last one is new: the two clocks drift apart by ~50 ppm, seconds over days of uptime.
        """
        u = self.unit(serial)
        last = u.get("boot_wall")
        if known_new or last is None or abs(float(last) - boot_wall) > tolerance_s:
            u["boot_count"] = int(u.get("boot_count", 0)) + 1
        u["boot_wall"] = boot_wall
        self.save()
        return int(u["boot_count"])

    def boot_params(self, serial: int, boot_count: int, read_now: dict[str, float]) -> dict[str, float]:
        """The compensation parameters as they were at the start of boot ``boot_count``: those kept for
        it if this boot was seen before (a daemon restarted within it, after its own writes), else
        ``read_now``, which are then kept for it."""
        u = self.unit(serial)
        kept = u.get("boot_params")
        if isinstance(kept, dict) and u.get("boot_params_boot") == boot_count:
            return {str(k): float(v) for k, v in kept.items()}
        u["boot_params"] = {str(k): float(v) for k, v in read_now.items()}
        u["boot_params_boot"] = int(boot_count)
        self.save()
        return dict(read_now)

    def keep_range(self, serial: int, version: int, lo: float, hi: float, replace: bool = False) -> None:
        """The range [degC] ``version`` was (or is to be) written with, for a rollback or an operator's
        file (``replace``: it overrides one kept); the last KEPT_RANGES versions are kept."""
        ranges = self.unit(serial).setdefault("ranges", {})
        if replace or str(version) not in ranges:
            ranges[str(version)] = [float(lo), float(hi)]
        for old in sorted(ranges, key=int)[:-KEPT_RANGES]:
            del ranges[old]

    def widen(self, serial: int, lo: float, hi: float) -> tuple[float, float]:
        """Merge [lo, hi] degC into the unit's seen range and return the union."""
        u = self.unit(serial)
        old = u.get("temp_range")
        rng = (min(lo, old[0]), max(hi, old[1])) if old else (lo, hi)
        u["temp_range"] = [float(rng[0]), float(rng[1])]
        return rng

    def save(self) -> None:
        if self.path is None:
            return
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps({"units": self.units}, indent=1, sort_keys=True), encoding="utf-8")
            os.replace(tmp, self.path)
        except OSError as err:
            log.error(
                "mavlink state %s cannot be written (%s); the version survives only in memory", self.path, err
            )
