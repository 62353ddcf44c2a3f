"""``scancell daemon --config CELL.toml``: the cell service (devices, commands, jobs)."""

from __future__ import annotations

import argparse
from dataclasses import replace

from scancell.cli._common import default_cell_config, fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None,
                   help="cell config TOML (default: the packaged deploy/cells/sim.toml)")
    p.add_argument("--listen", default=None,
                   help="override [bus] listen endpoints, comma-separated")
    p.add_argument("--cell", default=None, help="override [cell] name")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                   help="override any config key, e.g. --set simulator.robot.motion_port=12000 "
                        "--set devices.robot.motion_port=12000 (repeatable)")


def main(args: argparse.Namespace) -> int:
    from scancell.config import ConfigError, load_cell_config, merge_overrides

    path = args.config or default_cell_config()
    try:
        overrides = merge_overrides(args.set)
        if args.cell:
            overrides.setdefault("cell", {})["name"] = args.cell
        cfg = load_cell_config(path, overrides)
    except ConfigError as exc:
        return fail("daemon", str(exc))
    bus = cfg.bus
    if args.listen:
        bus = replace(bus, listen=tuple(e.strip() for e in args.listen.split(",") if e.strip()))
    from scancell.daemon.service import SimulatorError, run_daemon

    try:
        return run_daemon(cfg, bus)
    except ConnectionError as exc:
        return fail("daemon", f"{exc} (is another daemon using that port?)")
    except SimulatorError as exc:
        return fail("daemon", str(exc))
