"""configs/gyrocal.service passes `systemd-analyze verify` silently and scores low on `security`;
configs/99-gyrocal-imu.rules is well-formed udev syntax.

systemd is not PID 1 on the development machines, but systemd-analyze works offline on a unit file.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "configs" / "gyrocal.service"
RULES = REPO / "configs" / "99-gyrocal-imu.rules"
DOCS = REPO / "docs" / "operations.md"
ANALYZE = shutil.which("systemd-analyze")
MAX_EXPOSURE = 1.7  # issue 8 acceptance: at or below 1.7 (measured 1.7 with systemd 252)

needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed")


def unit_settings() -> dict[str, list[str]]:
    """Key -> values (a key may repeat) from the unit file, comments and sections ignored."""
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";", "[")):
            continue
        key, _, value = line.partition("=")
        out.setdefault(key.strip(), []).append(value.strip())
    return out


def runnable_copy(tmp_path: Path) -> Path:
    """The unit with ExecStart's binary swapped for one that exists here.

    `verify` checks that the ExecStart binary exists and is executable; /usr/local/bin/gyrocal exists
    on an installed nav computer, not on a development machine. Only that path changes: the
    arguments and every other line stay, so the check covers the file we ship.
    """
    exe = Path(sys.executable).with_name("gyrocal")
    if not exe.exists():
        exe = Path("/bin/true")
    text = UNIT.read_text()
    assert text.count("ExecStart=/usr/local/bin/gyrocal ") == 1
    copy = tmp_path / "gyrocal.service"  # the unit name must stay gyrocal.service
    copy.write_text(text.replace("ExecStart=/usr/local/bin/gyrocal ", f"ExecStart={exe} "))
    return copy


@needs_analyze
def test_systemd_analyze_verify_prints_nothing(tmp_path: Path) -> None:
    proc = subprocess.run([ANALYZE, "verify", str(runnable_copy(tmp_path))], capture_output=True, text=True,
                          timeout=60)
    assert (proc.stdout + proc.stderr).strip() == "", proc.stdout + proc.stderr
    assert proc.returncode == 0


@needs_analyze
def test_systemd_analyze_security_exposure_is_low() -> None:
    proc = subprocess.run([ANALYZE, "security", "--offline=true", str(UNIT)], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    m = re.search(r"Overall exposure level for gyrocal\.service:\s*([0-9.]+)\s+(\w+)", proc.stdout)
    assert m, proc.stdout[-500:]
    score, verdict = float(m.group(1)), m.group(2)
    assert score <= MAX_EXPOSURE and verdict == "OK", f"exposure {score} {verdict}"


def test_unit_declares_the_service_contract() -> None:
    s = unit_settings()
    expected = {
        "Type": "notify", "NotifyAccess": "main", "WatchdogSec": "10", "Restart": "on-failure",
        "ExecStart": "/usr/local/bin/gyrocal run --config /etc/gyrocal/gyrocal.yaml",
        "ExecReload": "/bin/kill -HUP $MAINPID", "KillSignal": "SIGTERM",
        "StateDirectory": "gyrocal", "RuntimeDirectory": "gyrocal", "RuntimeDirectoryMode": "0750",
        "User": "gyrocal", "Group": "gyrocal", "SupplementaryGroups": "dialout",
        "ProtectSystem": "strict", "NoNewPrivileges": "yes", "PrivateTmp": "yes", "DevicePolicy": "closed",
    }
    for key, value in expected.items():
        assert s.get(key) == [value], f"{key}: {s.get(key)}"
    assert "char-ttyUSB rw" in s["DeviceAllow"] and "char-ttyACM rw" in s["DeviceAllow"]
    families = s["RestrictAddressFamilies"][0].split()
    assert {"AF_UNIX", "AF_CAN", "AF_NETLINK", "AF_INET", "AF_INET6"} == set(families)
    for key in ("RestartSec", "TimeoutStopSec"):
        assert key in s


def test_unit_has_no_hardening_that_would_cut_the_links() -> None:
    """PrivateDevices hides the tty, PrivateNetwork hides can0, PrivateUsers unmaps dialout."""
    s = unit_settings()
    for key in ("PrivateDevices", "PrivateNetwork", "PrivateUsers"):
        assert s.get(key, ["no"]) == ["no"], key


UDEV_ASSIGN = re.compile(r'^(?P<key>[A-Z_]+)(\{(?P<attr>[^}]+)\})?(?P<op>==|!=|\+=|-=|:=|=)"(?P<val>[^"]*)"$')


def udev_rules() -> list[list[tuple[str, str | None, str, str]]]:
    rules = []
    for line in RULES.read_text().splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = []
        for item in re.split(r",\s*", line.strip()):
            m = UDEV_ASSIGN.match(item)
            assert m, f"not udev syntax: {item!r}"
            parts.append((m["key"], m["attr"], m["op"], m["val"]))
        rules.append(parts)
    return rules


def test_udev_rule_gives_a_stable_name_with_dialout_access() -> None:
    (rule,) = udev_rules()
    keys = {(k, a): (op, v) for k, a, op, v in rule}
    assert keys[("SUBSYSTEM", None)] == ("==", "tty")
    for attr in ("idVendor", "idProduct", "serial"):
        assert keys[("ATTRS", attr)][0] == "=="
    assert keys[("SYMLINK", None)] == ("+=", "gyrocal-imu")
    assert keys[("GROUP", None)] == ("=", "dialout")
    assert keys[("MODE", None)] == ("=", "0660")


def test_operations_doc_states_the_security_command_and_score() -> None:
    text = DOCS.read_text()
    assert "systemd-analyze security --offline=true configs/gyrocal.service" in text
    assert re.search(r"exposure level[^\n]*\b1\.7\b", text)
