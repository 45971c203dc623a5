"""Readers: every log format gyrocal reads, each turned into one ``LogData`` (docs/logformat.md).

One small module per format, found by name in ``READERS`` and imported on first use (as python-can
finds interfaces), so ``gyrocal fit run.csv`` never imports pyulog, pymavlink or rosbags:

- ``csv``: our CSV log, or any CSV with ``--columns`` (a column map) and ``--units``;
- ``can``: a python-can log (.asc, .blf, candump .log, .trc, .mf4, ...) decoded with our DBC;
- ``serial``: a capture of the serial protocol's raw bytes (.cap, .raw, .serial);
- ``ulog``: PX4 .ulg (sensor_gyro_fifo + sensor_accel_fifo, or sensor_gyro + sensor_accel, of one
  instance; or sensor_combined);
- ``dataflash``: ArduPilot .bin (IMU messages of one instance);
- ``tlog``: MAVLink telemetry log .tlog (HIGHRES_IMU > SCALED_IMU(n) > RAW_IMU of one instance);
- ``rosbag``: rosbag2 (.mcap, .db3 or its directory) or ROS 1 .bag sensor_msgs/msg/Imu.

Each reader converts to deg/s, g, degC and s, and counts what it dropped, by reason, in
``LogData.dropped``.
"""

from __future__ import annotations

import argparse
import codecs
import importlib
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

from gyrocal.errors import ConfigError, LogFormatError
from gyrocal.logformat import OPTIONAL, REQUIRED, LogData

READERS: dict[str, tuple[str, str]] = {
    "csv": ("gyrocal.readers.csvlog", "read_csv"),
    "can": ("gyrocal.readers.canlog", "read_canlog"),
    "serial": ("gyrocal.readers.serialcap", "read_serial_capture"),
    "ulog": ("gyrocal.readers.ulog", "read_ulog"),
    "dataflash": ("gyrocal.readers.dataflash", "read_dataflash"),
    "tlog": ("gyrocal.readers.tlog", "read_tlog"),
    "rosbag": ("gyrocal.readers.rosbag", "read_rosbag"),
}
"""Format kind -> (module, function(path, options) -> LogData)."""

EXTENSIONS: dict[str, str] = {
    ".csv": "csv", ".txt": "csv",
    ".asc": "can", ".blf": "can", ".log": "can", ".trc": "can", ".mf4": "can", ".csv.can": "can",
    ".cap": "serial", ".raw": "serial", ".serial": "serial",
    ".ulg": "ulog",
    ".bin": "dataflash",
    ".tlog": "tlog",
    ".mcap": "rosbag", ".db3": "rosbag", ".bag": "rosbag",
}
"""File extension -> kind; ``--format`` overrides. A .bin that does not start with DataFlash's
0xA3 0x95 header is taken as a serial capture."""

DATAFLASH_HEAD = b"\xa3\x95"


@dataclass
class ReadOptions:
    """What a reader may need beyond the path (all optional).

    columns: our column name -> the file's (CSV); units: quantity -> unit (CSV);
    instance: which IMU of several (ULog, DataFlash, .tlog; default 0); topic: which topic or message
    (ULog: sensor_gyro_fifo, sensor_gyro or sensor_combined; .tlog: the IMU message; ROS: the Imu
    topic); dbc: the CAN database.
    """

    columns: dict[str, str] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    instance: int = 0
    topic: str | None = None
    dbc: str | None = None


def detect_kind(path: str | Path) -> str:
    """The reader kind for ``path``, from its extension (and a .bin's first bytes)."""
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").exists():
            return "rosbag"
        raise ConfigError(f"{p}: a directory, but not a rosbag2 bag (no metadata.yaml)")
    suffix = p.suffix.lower()
    if suffix == ".bin":
        try:
            with p.open("rb") as fh:
                head = fh.read(2)
        except OSError as err:
            raise LogFormatError(f"{p}: cannot open the log ({err.strerror})") from err
        return "dataflash" if head == DATAFLASH_HEAD else "serial"
    if suffix == ".gz" and p.name.lower().endswith((".asc.gz", ".blf.gz", ".log.gz", ".trc.gz")):
        return "can"
    kind = EXTENSIONS.get(suffix)
    if kind is None:
        raise ConfigError(f"{p}: unknown log extension {suffix!r}; give --format "
                          f"{{{','.join(READERS)}}} (docs/logformat.md)")
    return kind


def read_any(path: str | Path, kind: str | None = None, options: ReadOptions | None = None) -> LogData:
    """Read a log of any supported format into LogData (deg/s, g, degC, s)."""
    kind = kind or detect_kind(path)
    if kind not in READERS:
        raise ConfigError(f"--format {kind!r} unknown; choose one of {', '.join(READERS)}")
    module, func = READERS[kind]
    try:
        log: LogData = getattr(importlib.import_module(module), func)(str(path), options or ReadOptions())
    except UnicodeDecodeError as err:  # it ended in a traceback (a Latin-1 "degC" in a comment: rc36b H4)
        raise LogFormatError(not_utf8(path, err) or str(err)) from None
    previous = log.metadata.get("format")
    if previous and previous != kind:  # a converted log keeps where it came from
        log.metadata["source_format"] = previous
    log.metadata["format"] = kind
    from gyrocal.readers.plausible import drop_implausible

    return drop_implausible(log)


def not_utf8(path: str | Path, err: UnicodeDecodeError | None = None) -> str | None:
    """For a text log that is not UTF-8, one line: the file, the line and byte, and the fix; None
    when it is UTF-8. Read in 16 MB pieces: a streamed log is never read whole."""
    dec = codecs.getincrementaldecoder("utf-8")()
    offset, lines = 0, 1
    try:
        with Path(path).open("rb") as fh:
            while piece := fh.read(1 << 24):
                try:
                    dec.decode(piece)
                except UnicodeDecodeError as bad:
                    at = max(bad.start - len(dec.getstate()[0]), 0)  # bytes held back from before
                    line = lines + piece.count(b"\n", 0, at)
                    return (f"{path}: not UTF-8 text at line {line} (byte {offset + at}: 0x{piece[at]:02x}): "
                            f"{bad.reason}; save it as UTF-8 (e.g. iconv -f latin1 -t utf-8), a degree "
                            "sign in a comment too")
                offset, lines = offset + len(piece), lines + piece.count(b"\n")
    except OSError:
        pass
    return None if err is None else f"{path}: not UTF-8 text: {err.reason}; save it as UTF-8"


def require(module: str, what: str) -> ModuleType:
    """Import an optional dependency, or raise ConfigError naming the extra that provides it."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ConfigError(f"{what} needs the Python package {module.split('.')[0]!r}: "
                          "pip install 'gyrocal[formats]'") from err


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The reader flags shared by fit, analyze, convert and replay."""
    g = parser.add_argument_group("log format (docs/logformat.md)")
    g.add_argument("--format", choices=list(READERS), help="the log's format (default: by its extension)")
    g.add_argument("--columns", metavar="MAP",
                   help="CSV column map, ours=theirs, e.g. t=time,wx=gyro_x,wy=gyro_y,wz=gyro_z,ax=acc_x,...")
    g.add_argument("--units", metavar="UNITS",
                   help="the units the log holds, e.g. gyro=rad/s,accel=m/s^2,temp=K,time=ms "
                        "(default: its '# units:' line, else deg/s, g, degC, s)")
    g.add_argument("--instance", type=int, default=0, metavar="N",
                   help="which IMU of several in a .ulg, .bin or .tlog; a CAN log: the unit's node id "
                        "(default 0)")
    g.add_argument("--topic", metavar="NAME",
                   help="ULog topic (sensor_gyro_fifo, sensor_gyro or sensor_combined), .tlog message "
                        "(HIGHRES_IMU, SCALED_IMU, SCALED_IMU2/3, RAW_IMU) or ROS Imu topic (default: found)")
    g.add_argument("--dbc", metavar="FILE.dbc", help="CAN database for python-can logs (default: shipped)")


def options_from_args(args: argparse.Namespace) -> ReadOptions:
    """ReadOptions from the flags of ``add_arguments``; ConfigError names a malformed flag."""
    from gyrocal.readers.units import parse_units

    columns: dict[str, str] = {}
    for item in (getattr(args, "columns", None) or "").split(","):
        if not item.strip():
            continue
        ours, sep, theirs = item.partition("=")
        if not sep or not ours.strip() or not theirs.strip():
            raise ConfigError(f"--columns: {item!r} is not OURS=THEIRS (e.g. wx=gyro_x)")
        if ours.strip() not in (*REQUIRED, *OPTIONAL):
            # a typo (tmp=temp_K) left temp out of the log with no word: a foreign-log audit
            raise ConfigError(f"--columns: {ours.strip()!r} is not one of our columns "
                              f"({', '.join((*REQUIRED, *OPTIONAL))}); write OURS=THEIRS, e.g. temp=temp_K")
        columns[ours.strip()] = theirs.strip()
    units = parse_units(args.units) if getattr(args, "units", None) else {}
    return ReadOptions(columns, units, getattr(args, "instance", 0) or 0, getattr(args, "topic", None),
                       getattr(args, "dbc", None))


def read_from_args(path: str, args: argparse.Namespace) -> LogData:
    """``read_any`` with the command line's reader flags."""
    return read_any(path, getattr(args, "format", None), options_from_args(args))


def accounting(log: LogData) -> dict:
    """What the reader used and dropped, for a command's JSON: rows in the source, rows kept, by reason."""
    return {"source_rows": int(log.data_rows or len(log) + sum(log.dropped.values())),
            "rows": len(log), "dropped": dict(log.dropped), "warnings": list(log.warnings)}
