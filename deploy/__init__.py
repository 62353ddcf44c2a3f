"""Deployment files: cell configs, router configs, systemd units (see deploy/README.md)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

#: The cell config ``scancell daemon`` and ``scancell demo`` use when none is given.
DEFAULT_CELL = "sim"


def cell_config_path(name: str) -> Path:
    """Path of a packaged cell config, e.g. ``cell_config_path("sim")``."""
    return Path(str(resources.files("scancell.deploy") / "cells" / f"{name}.toml"))


def default_cell_config() -> Path:
    return cell_config_path(DEFAULT_CELL)
