"""``gyrocal install-files DIR``: write the shipped example config, systemd unit and udev rule to DIR.

Why: a wheel installed with pip has no ``configs/`` folder to copy from, yet docs/operations.md
installs these three files (and the CAN database, for tools such as cantools and can.viewer). They
are package data (gyrocal/configs/), so every install can write them out, then copy them into place:

    gyrocal install-files /tmp/gyrocal-files
    sudo install -m 0644 /tmp/gyrocal-files/gyrocal.example.yaml /etc/gyrocal/gyrocal.yaml
    sudo install -m 0644 /tmp/gyrocal-files/gyrocal.service /etc/systemd/system/
    sudo install -m 0644 /tmp/gyrocal-files/99-gyrocal-imu.rules /etc/udev/rules.d/

The unit's ExecStart names /usr/local/bin/gyrocal; ``--exec`` writes the path of this install's
``gyrocal`` instead (e.g. a venv's), which is the one line an operator otherwise edits by hand.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from importlib import resources
from pathlib import Path

from gyrocal.errors import ConfigError

SHIPPED = ("gyrocal.example.yaml", "gyrocal.service", "99-gyrocal-imu.rules", "gyrocal.dbc")
UNIT_EXEC = "/usr/local/bin/gyrocal"


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, metavar="DIR", help="where to write the files (created if missing)")
    p.add_argument("--force", action="store_true", help="overwrite files that exist in DIR")
    p.add_argument("--exec", dest="exec_path", nargs="?", const="", default=None, metavar="PATH",
                   help=f"write PATH (default: this install's gyrocal) in the unit's ExecStart instead of "
                        f"{UNIT_EXEC}; give DIR first (`install-files DIR --exec`), since --exec DIR "
                        "reads DIR as PATH")


def shipped_text(name: str) -> str:
    """One shipped file's text, from the installed package (works from a wheel and a checkout)."""
    return (resources.files("gyrocal") / "configs" / name).read_text(encoding="utf-8")


def main(args: argparse.Namespace) -> int:
    out: Path = args.dir
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"{out}: cannot create the directory ({err.strerror}); "
                          "fix: choose a writable DIR") from None
    clash = [n for n in SHIPPED if (out / n).exists()]
    if clash and not args.force:
        raise ConfigError(f"{out}: {', '.join(clash)} already there; fix: pass --force to overwrite, or "
                          "choose an empty DIR")
    for name in SHIPPED:
        text = shipped_text(name)
        if name == "gyrocal.service" and args.exec_path is not None:
            exe = args.exec_path or shutil.which("gyrocal") or str(Path(sys.executable).with_name("gyrocal"))
            text = text.replace(f"ExecStart={UNIT_EXEC} ", f"ExecStart={exe} ")
        (out / name).write_text(text, encoding="utf-8")
        print(out / name)
    return 0
