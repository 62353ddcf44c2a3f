"""``scancell monitor``: the cell live in the Foxglove app, over Foxglove's WebSocket protocol."""

from __future__ import annotations

import argparse
from typing import Any

from scancell.cli._common import add_bus_arguments, serve


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_bus_arguments(p)
    p.add_argument("--host", default="127.0.0.1", help="WebSocket address (0.0.0.0: every "
                                                       "interface)")
    p.add_argument("--port", type=int, default=8765)
    p.add_argument("--topics", nargs="+", default=["**"],
                   help="key expressions under scancell/<cell>/ to show")
    p.add_argument("--max-hz", type=float, default=2.0, help="images and clouds per second")
    p.add_argument("--max-image-width", type=int, default=640)
    p.add_argument("--max-cloud-points", type=int, default=200_000)


def main(args: argparse.Namespace) -> int:
    from scancell.bus.protocol import BusLike
    from scancell.workers.monitor import Monitor, MonitorSettings

    settings = MonitorSettings(tuple(args.topics), args.max_hz, args.max_image_width,
                               args.max_cloud_points)
    monitors: list[Any] = []

    def make(bus: BusLike) -> Monitor:
        monitors.append(Monitor(bus, settings, args.host, args.port))
        return monitors[0]

    return serve(args, "monitor", make,
                 lambda bus: f"monitor of cell {bus.keys.cell!r}: open Foxglove and connect to "
                             f"ws://{args.host}:{monitors[0].port}")
