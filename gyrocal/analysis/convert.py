"""``gyrocal convert DATASET [SRC] OUT.csv`` or ``gyrocal convert LOG OUT.csv``: to the CSV log format.

Each shipped dataset has a loader in ``gyrocal.datasets`` (imported lazily) that converts units to
deg/s, g, degC and s; SRC defaults to the project's copy in data/. Any log a reader takes (.ulg,
.bin, .asc/.blf, rosbag2, a CSV with --columns/--units) converts the same way (docs/logformat.md).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from gyrocal.errors import ConfigError
from gyrocal.logformat import LogData, write_log
from gyrocal.readers import add_arguments, read_from_args

LOADERS: dict[str, tuple[str, str]] = {
    "imu_tk": ("gyrocal.datasets.imu_tk", "load_imu_tk"),
    "mikoff": ("gyrocal.datasets.mikoff", "load_mikoff"),
    "imucal": ("gyrocal.datasets.imucal", "load_imucal"),
    "tomisuarez": ("gyrocal.datasets.tomisuarez", "load_tomisuarez"),
    "sunsided": ("gyrocal.datasets.sunsided", "load_sunsided"),
}


def load_dataset(name: str, src: str | None = None) -> LogData:
    """Load a dataset by name; ConfigError names the known datasets when ``name`` is unknown."""
    if name not in LOADERS:
        raise ConfigError(f"dataset {name!r} unknown; choose one of {', '.join(LOADERS)}")
    module, func = LOADERS[name]
    return getattr(importlib.import_module(module), func)(src)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help=f"a shipped dataset ({', '.join(LOADERS)}) or a log file to convert")
    parser.add_argument("paths", nargs="+", metavar="PATH",
                        help="[SRC] OUT.csv: an optional source file/folder (default: data/<dataset>), "
                             "then the output log")
    add_arguments(parser)


def main(args: argparse.Namespace) -> int:
    if len(args.paths) > 2:
        raise ConfigError("convert takes at most SRC and OUT.csv")
    src, out = (None, args.paths[0]) if len(args.paths) == 1 else args.paths
    if args.dataset not in LOADERS and Path(args.dataset).exists():
        if src is not None:
            raise ConfigError("convert LOG OUT.csv takes no SRC")
        log = read_from_args(args.dataset, args)
        for w in log.warnings:
            print(f"gyrocal: warning: {w}", file=sys.stderr)
        if log.dropped:
            print(f"{args.dataset}: dropped " + ", ".join(f"{v} {k}" for k, v in log.dropped.items()),
                  file=sys.stderr)
    elif args.dataset not in LOADERS and ("/" in args.dataset or "." in Path(args.dataset).name):
        raise ConfigError(f"{args.dataset}: no such file; give a log file that exists, or a shipped dataset "
                          f"({', '.join(LOADERS)})")
    else:
        log = load_dataset(args.dataset, src)
    if len(log) == 0:  # analyze refuses such a file: so does convert, rather than write one
        lost = f" ({', '.join(f'{v} {k}' for k, v in log.dropped.items())})" if log.dropped else ""
        raise ConfigError(f"{args.dataset}: no sample could be read{lost}; nothing written to {out}. "
                          "Check --format (or the file's kind) and --columns")
    order = [c for c in ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session") if c in log.columns]
    meta = dict(log.metadata)
    if log.dropped:  # the converted log says what its source lost
        meta["dropped"] = " ".join(f"{k}={v}" for k, v in log.dropped.items())
    write_log(out, log.columns, meta, order + [c for c in log.columns if c not in order])
    print(f"{out}: {len(log)} samples from {log.source}", file=sys.stderr)
    return 0
