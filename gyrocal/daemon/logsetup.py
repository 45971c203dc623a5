"""Logging to stderr in a form journald shows well, and the one -v/-q verbosity of every command.

Why stderr: stdout carries results (tables, ``--json``), so ``gyrocal demo --json --verbose | jq``
must see JSON only; every log line, warning and fatal error goes to stderr.

Under systemd each line starts with a syslog priority prefix such as ``<4>``, which journald turns
into the entry's priority (so ``journalctl -p warning`` works) and strips from the text; journald adds
its own timestamps. "Under systemd" means what systemd.exec(5) says: $JOURNAL_STREAM holds the
device and inode of the stream connected to the journal, and it is ours only if stderr is that very
stream (a child whose stderr was redirected to a file must not write prefixes into it). On a terminal
we print a timestamp instead.
"""

from __future__ import annotations

import errno
import logging
import os
import sys

_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}
_LEVELS = ["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"]
_shift = 0  # -v minus -q of this process's command line (set once by gyrocal.cli)


def journal_stream() -> bool:
    """True when stderr is connected to the journal (systemd's $JOURNAL_STREAM names its dev:ino)."""
    value = os.environ.get("JOURNAL_STREAM", "")
    if not value:
        return False
    try:
        dev, ino = (int(x) for x in value.split(":"))
    except ValueError:
        return False  # not systemd's dev:ino
    try:
        st = os.fstat(sys.stderr.fileno())
    except (OSError, ValueError, AttributeError):
        return True  # stderr swapped in-process (no file descriptor): trust the variable
    return (st.st_dev, st.st_ino) == (dev, ino)


def priority_prefix(levelno: int) -> str:
    """``<N>`` for journald when stderr is the journal, else nothing."""
    return f"<{_PRIORITY.get(levelno, 6)}>" if journal_stream() else ""


def set_verbosity(verbose: int, quiet: int) -> None:
    """Each -v lowers every command's log threshold one level (INFO -> DEBUG), each -q raises it."""
    global _shift
    _shift = int(verbose) - int(quiet)


def effective_level(base: str) -> str:
    """``base`` (the command's default or its --log-level) moved by -v/-q, clamped to DEBUG..CRITICAL."""
    name = str(base).upper()
    i = _LEVELS.index(name) if name in _LEVELS else _LEVELS.index("WARNING")
    return _LEVELS[max(0, min(len(_LEVELS) - 1, i - _shift))]


class _JournalFormatter(logging.Formatter):
    """``<prio>name: message``, the prefix repeated on every line of a multi-line record (a traceback):
    journald makes one entry per line, and a line without a prefix would be filed at info level."""

    def format(self, record: logging.LogRecord) -> str:
        prio = _PRIORITY.get(record.levelno, 6)
        first, *rest = super().format(record).split("\n")
        return "\n".join([f"<{prio}>{record.name}: {first}", *(f"<{prio}>{line}" for line in rest)])


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is at the time of the record, not at set-up (tests swap it)."""

    gyrocal = True  # marks the handler setup_logging owns (others, e.g. pytest's, are left alone)

    @property  # type: ignore[override]
    def stream(self):  # noqa: ANN201
        return sys.stderr

    @stream.setter
    def stream(self, _value: object) -> None:
        pass

    def handleError(self, record: logging.LogRecord) -> None:  # noqa: N802 (logging's name)
        """A closed stderr (``2>&1 | head``) is not worth a traceback on the same closed stderr."""
        err = sys.exc_info()[1]
        if isinstance(err, BrokenPipeError) or (isinstance(err, OSError) and err.errno == errno.EPIPE):
            return
        super().handleError(record)


def setup_logging(level: str = "INFO") -> None:
    """Send every log line to stderr at ``level`` moved by -v/-q (idempotent: one handler)."""
    handler = _StderrHandler()
    if journal_stream():
        handler.setFormatter(_JournalFormatter("%(message)s"))
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                                               "%H:%M:%S"))
    root = logging.getLogger()
    root.handlers[:] = [h for h in root.handlers if not getattr(h, "gyrocal", False)] + [handler]
    root.setLevel(effective_level(level))
