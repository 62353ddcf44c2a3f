"""``scancell daemon``."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from scancell.config import ConfigError, load_cell_config, merge_overrides
from scancell.deploy import default_cell_config


def main(args: argparse.Namespace) -> int:
    path = args.config or default_cell_config()
    try:
        overrides = merge_overrides(args.set)
        if args.cell:
            overrides.setdefault("cell", {})["name"] = args.cell
        cfg = load_cell_config(path, overrides)
    except ConfigError as exc:
        print(f"scancell daemon: {exc}", file=sys.stderr)
        return 2
    bus = cfg.bus
    if args.listen:
        bus = replace(bus, listen=tuple(e.strip() for e in args.listen.split(",") if e.strip()))
    from scancell.daemon.service import SimulatorError, run_daemon

    try:
        return run_daemon(cfg, bus)
    except ConnectionError as exc:
        print(f"scancell daemon: {exc} (is another daemon using that port?)", file=sys.stderr)
        return 2
    except SimulatorError as exc:
        print(f"scancell daemon: {exc}", file=sys.stderr)
        return 2
