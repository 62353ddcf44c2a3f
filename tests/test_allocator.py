"""The long-running services keep freed memory (cli/_allocator.py)."""

from __future__ import annotations

import sys

import pytest
from scancell.cli import COMMANDS, LONG_RUNNING
from scancell.cli._allocator import keep_freed_memory


@pytest.mark.unit
def test_the_services_keep_freed_memory_where_glibc_lets_them():
    assert LONG_RUNNING <= set(COMMANDS)
    if sys.platform.startswith("linux"):
        assert keep_freed_memory() is True  # the CI machine: glibc
    else:
        assert keep_freed_memory() is False
