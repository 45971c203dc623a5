"""Reader ``csv``: our CSV log, or another CSV through a column map and declared units.

The parsing (line and column named on a bad value, NaN/Inf rows counted and dropped) is
``gyrocal.logformat.read_log``'s; this module only passes the ``--columns``/``--units`` options.
"""

from __future__ import annotations

from gyrocal.logformat import LogData, read_log
from gyrocal.readers import ReadOptions


def read_csv(path: str, options: ReadOptions) -> LogData:
    """Read a CSV log; ``options.columns`` maps our names to the file's, ``options.units`` its units."""
    return read_log(path, rename=options.columns or None, units=options.units or None)
