"""The one ``gyrocal`` command and its subcommands.

Subcommands live in their own modules and are imported lazily (as python-can finds interfaces),
so ``gyrocal status`` does not pay for numpy/scipy/matplotlib imports it never uses. Each module
exposes ``configure(parser)`` and ``main(args) -> int``. Any GyrocalError reaches the user as one
line on stderr with exit status 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from gyrocal import __version__
from gyrocal.errors import GyrocalError

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("gyrocal.daemon.demo", "run the daemon against the virtual unit, push, check the drift"),
    "run": ("gyrocal.daemon.cli_run", "the calibrator daemon (systemd service)"),
    "sim": ("gyrocal.sim.cli_sim", "the virtual strapdown unit on a pty or a CAN bus"),
    "fit": ("gyrocal.model.cli_fit", "fit drift coefficients to a log (formats: docs/logformat.md)"),
    "analyze": ("gyrocal.analysis.cli_analyze", "what the simulation gets wrong in a log (docs/analysis.md)"),
    "convert": ("gyrocal.analysis.convert", "turn a shipped real dataset into the log format"),
    "replay": ("gyrocal.replay.cli_replay", "run the daemon's engine on a recording (or play it into a pty)"),
    "status": ("gyrocal.daemon.cli_control", "state of a running daemon"),
    "recalibrate": ("gyrocal.daemon.cli_control", "start a new calibration session now"),
    "rollback": ("gyrocal.daemon.cli_control", "push an earlier calibration version"),
    "push": ("gyrocal.daemon.cli_control", "push a coefficient set from a file"),
}


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gyrocal", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"gyrocal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if name == wanted:  # only the chosen command's module is imported
            mod = importlib.import_module(module)
            configure = getattr(mod, f"configure_{name}", None) or mod.configure
            configure(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser(argv)
        args = parser.parse_args(argv)
        if not getattr(args, "command", None):
            parser.print_help()
            return 2
        mod = importlib.import_module(args._module)
        run = getattr(mod, f"main_{args.command}", None) or mod.main
        return int(run(args) or 0)
    except GyrocalError as err:
        print(f"gyrocal: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
