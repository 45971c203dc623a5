"""Suite-wide fixtures."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def _restore_root_logging() -> Iterator[None]:
    """Tests that run a command in process call setup_logging, which sets the root logger's level and
    handler; restore both so that a later test in the same worker (pytest-xdist) still sees its logs
    in caplog, whatever order the tests run in."""
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    root.setLevel(level)
    root.handlers[:] = handlers


@pytest.fixture(autouse=True, scope="session")
def _port_claims_in_a_temporary_directory(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Serial links claim their port in /run/lock (serial_link.py): the suite's, daemons it starts
    included, go to a directory of its own, so a test never leaves a file on the machine."""
    os.environ["GYROCAL_LOCK_DIR"] = str(tmp_path_factory.mktemp("locks"))
