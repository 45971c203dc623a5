"""``gyrocal convert DATASET [SRC] OUT.csv``: turn a shipped real dataset into a Contract 1 log.

Each dataset has a loader in ``gyrocal.datasets`` (imported lazily) that converts units to deg/s,
g, degC and s. SRC defaults to the project's copy in data/.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from gyrocal.errors import ConfigError
from gyrocal.logformat import LogData, write_log

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
    parser.add_argument("dataset", help=f"which shipped dataset: {', '.join(LOADERS)}")
    parser.add_argument("paths", nargs="+", metavar="PATH",
                        help="[SRC] OUT.csv: an optional source file/folder (default: data/<dataset>), "
                             "then the output log")


def main(args: argparse.Namespace) -> int:
    if len(args.paths) > 2:
        raise ConfigError("convert takes at most SRC and OUT.csv")
    src, out = (None, args.paths[0]) if len(args.paths) == 1 else args.paths
    log = load_dataset(args.dataset, src)
    order = [c for c in ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session") if c in log.columns]
    write_log(out, log.columns, log.metadata, order + [c for c in log.columns if c not in order])
    print(f"{out}: {len(log)} samples from {log.source}", file=sys.stderr)
    return 0
