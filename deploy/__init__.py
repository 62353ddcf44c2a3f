"""Deployment files: cell configs, router configs, systemd units (see deploy/systemd/README.md
and docs/tutorials/first-real-cell.md). This module only finds them inside the installed package."""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def deploy_file(*parts: str) -> Path:
    """Path of a packaged deployment file, e.g. ``deploy_file("zenoh", "router.json5")``."""
    return Path(str(resources.files("scancell.deploy").joinpath(*parts)))


def cell_config_path(name: str) -> Path:
    """Path of a packaged cell config, e.g. ``cell_config_path("sim")``."""
    return deploy_file("cells", f"{name}.toml")
