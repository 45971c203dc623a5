"""The one ``gyrocal`` command and its subcommands.

Subcommands live in their own modules and are imported lazily (as python-can finds interfaces),
so ``gyrocal status`` does not pay for numpy/scipy/matplotlib imports it never uses, and the daemon's
commands work without the ``[analysis]`` extra. Each module exposes ``configure(parser)`` and
``main(args) -> int``.

Conventions every command shares:
- stdout is for results (tables, JSON); logs and errors go to stderr (daemon/logsetup.py);
- ``-v``/``-q`` (repeatable, before or after the command) move the log threshold one level each from
  the command's default (``run``: INFO, the others: WARNING; ``--log-level`` where a command has it);
- any GyrocalError reaches the user as one line ``gyrocal: error: ...`` on stderr with exit status 2,
  with journald's ``<3>`` prefix under systemd, never as a traceback;
- a closed stdout (``gyrocal status --json | head -c 10``) ends the command quietly (status 141);
- a missing optional dependency names the extra that brings it (``pip install 'gyrocal[analysis]'``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from typing import NoReturn

from gyrocal import __version__
from gyrocal.daemon.logsetup import journal_stream, priority_prefix, set_verbosity, setup_logging
from gyrocal.errors import GyrocalError

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("gyrocal.daemon.demo", "run the daemon against the virtual unit, push, check the drift"),
    "run": ("gyrocal.daemon.cli_run", "the calibrator daemon (systemd service)"),
    "sim": ("gyrocal.sim.cli_sim", "the virtual strapdown unit on a pty or a CAN bus"),
    "fit": ("gyrocal.model.cli_fit", "fit drift coefficients to a recorded log (docs/logformat.md)"),
    "analyze": ("gyrocal.analysis.cli_analyze", "what the simulation gets wrong (docs/analysis.md)"),
    "convert": ("gyrocal.analysis.convert", "turn a shipped real dataset into the log format"),
    "replay": ("gyrocal.replay.cli_replay", "the daemon's engine on a recording, or a recording played live"),
    "status": ("gyrocal.daemon.cli_control", "state of a running daemon"),
    "recalibrate": ("gyrocal.daemon.cli_control", "start a new calibration session now"),
    "rollback": ("gyrocal.daemon.cli_control", "push an earlier calibration version"),
    "push": ("gyrocal.daemon.cli_control", "push a coefficient set from a file"),
    "install-files": ("gyrocal.install_files", "write the shipped config, systemd unit and udev rule to DIR"),
    "completion": ("gyrocal.completion", "print a shell completion script (bash)"),
}

DESCRIPTION = "gyrocal: on-line drift calibration of a strapdown gyro unit (daemon, simulator, analysis)."
EPILOG = """\
Results and JSON go to stdout, log lines and errors to stderr; -v/-q work before or after COMMAND.
`gyrocal COMMAND --help` for one command. Bash completion: gyrocal completion bash > \\
  ~/.local/share/bash-completion/completions/gyrocal. Daemon operation: docs/operations.md."""

DEFAULT_LOG_LEVEL = {"run": "INFO"}  # every other command: WARNING
EXTRAS = {"scipy": "analysis", "matplotlib": "analysis"}
"""Top-level packages of the optional extras -> the extra that installs them."""


class _Parser(argparse.ArgumentParser):
    """argparse with the journald priority on its usage-error line (a bad ExecStart= is a fatal error)."""

    def error(self, message: str) -> NoReturn:
        self.print_usage(sys.stderr)
        self.exit(2, f"{priority_prefix(logging.ERROR)}{self.prog}: error: {message}\n")


def _add_verbosity(p: argparse.ArgumentParser, dest: str) -> None:
    """-v/--verbose and -q/--quiet, skipping any spelling the command already defines for itself."""
    taken = set(p._option_string_actions)
    for flags, name, text in ((("-v", "--verbose"), "verbose", "more log lines on stderr (repeatable)"),
                              (("-q", "--quiet"), "quiet", "fewer log lines on stderr (repeatable)")):
        free = [f for f in flags if f not in taken]
        if free:
            p.add_argument(*free, action="count", default=0, dest=f"_{name}{dest}", help=text)


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = _Parser(prog="gyrocal", description=DESCRIPTION, epilog=EPILOG,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"gyrocal {__version__}")
    _add_verbosity(parser, "_top")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if name == wanted:  # only the chosen command's module is imported
            mod = importlib.import_module(module)
            configure = getattr(mod, f"configure_{name.replace('-', '_')}", None) or mod.configure
            configure(p)
        _add_verbosity(p, "")
    return parser


def _verbosity(args: argparse.Namespace) -> tuple[int, int]:
    verbose = getattr(args, "_verbose", 0) + getattr(args, "_verbose_top", 0)
    quiet = getattr(args, "_quiet", 0) + getattr(args, "_quiet_top", 0)
    if quiet and isinstance(getattr(args, "quiet", None), bool):
        args.quiet = True  # a command's own --quiet (analyze: no progress lines) follows -q too
    return verbose, quiet


def _missing_extra(err: ModuleNotFoundError, command: str | None) -> str | None:
    top = (err.name or "").split(".")[0]
    extra = EXTRAS.get(top)
    if extra is None:
        return None
    return (f"`gyrocal {command or ''}` needs {top}, which the lean install leaves out; install the "
            f"{extra} extra: pip install 'gyrocal[{extra}]'")


def _quiet_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush does not raise again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):
        pass


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    try:
        parser = build_parser(argv)
        args = parser.parse_args(argv)
        if not getattr(args, "command", None):
            parser.print_help()
            return 2
        set_verbosity(*_verbosity(args))
        setup_logging(getattr(args, "log_level", None) or DEFAULT_LOG_LEVEL.get(args.command, "WARNING"))
        mod = importlib.import_module(args._module)
        run = getattr(mod, f"main_{args.command.replace('-', '_')}", None) or mod.main
        code = int(run(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, inside the handler below, not at exit
        return code
    except GyrocalError as err:
        print(f"{priority_prefix(logging.ERROR)}gyrocal: error: {err}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as err:
        text = _missing_extra(err, command)
        if text is None:
            raise
        print(f"{priority_prefix(logging.ERROR)}gyrocal: error: {text}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        _quiet_stdout()
        return 141  # 128 + SIGPIPE, what a shell shows for a C tool stopped the same way
    except KeyboardInterrupt:
        return 130
    except Exception:
        if not journal_stream():
            raise  # a terminal shows Python's traceback as usual
        # under journald, a crash's traceback keeps its priority on every line (journalctl -p err)
        if not any(getattr(h, "gyrocal", False) for h in logging.getLogger().handlers):
            setup_logging("INFO")  # crashed before the command set logging up
        logging.getLogger("gyrocal").critical("gyrocal %s crashed", command or "", exc_info=True)
        return 1


if __name__ == "__main__":
    sys.exit(main())
