"""The small exception tree shared by every gyrocal module.

Each error is meant to reach a person as one line: the CLI prints ``str(err)`` and exits 2, so
messages name the file, the field (or line and column) and the fix.
"""


class GyrocalError(Exception):
    """Base of every error gyrocal raises on purpose."""


class ConfigError(GyrocalError):
    """A config file or option is wrong; the message names the file, the field and the fix."""


class LogFormatError(GyrocalError):
    """A log file does not follow Contract 1; the message names the line and the column."""


class LinkError(GyrocalError):
    """A link to the unit cannot be opened or used (unknown port, bus refused)."""


class ProtocolError(GyrocalError):
    """A frame cannot be encoded (a value out of its field's range, too many coefficients)."""


def yaml_error_text(name: str, err: Exception) -> str:
    """``NAME:LINE: not valid YAML (problem)``: one line, where PyYAML's own text is several with a
    caret drawing (a push file and the daemon's config say it alike)."""
    mark = getattr(err, "problem_mark", None)
    where = f":{mark.line + 1}:{mark.column + 1}" if mark is not None else ""
    return f"{name}{where}: not valid YAML ({getattr(err, 'problem', None) or err})"
