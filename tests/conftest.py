"""Suite-wide fixtures."""

from __future__ import annotations

import logging
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
