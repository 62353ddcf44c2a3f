"""``scancell replay FILE``: publish a recording again, as the live cell did."""

from __future__ import annotations

import argparse

from scancell.cli._common import DEFAULT_CELL, add_bus_arguments, bus_config, fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file")
    add_bus_arguments(p)
    p.add_argument("--listen", default=None,
                   help="be the bus hub on this endpoint instead of connecting to a daemon, "
                        "e.g. tcp/127.0.0.1:7447 (workers then connect here)")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor; 0 = as fast as possible")
    p.add_argument("--topics", nargs="+", default=None, help="key expressions to replay")
    p.add_argument("--start", type=float, default=None, help="seconds from the recording's start")
    p.add_argument("--end", type=float, default=None, help="seconds from the recording's start")
    p.add_argument("--wait", type=float, default=1.0,
                   help="seconds to wait for subscribers before publishing")


def main(args: argparse.Namespace) -> int:
    import time

    from scancell.bus import Bus, BusConfig, NoDaemon
    from scancell.recorder.reading import RecordingError, info
    from scancell.recorder.replay import replay

    try:
        rec = info(args.file)
    except RecordingError as exc:
        return fail("replay", str(exc))
    cell = args.cell or rec.cell or DEFAULT_CELL
    try:
        cfg = BusConfig(listen=(args.listen,)) if args.listen else bus_config(args)
    except ValueError as exc:
        return fail("replay", str(exc))
    try:
        bus = Bus.open(cfg, cell, wait_s=10.0)
    except (NoDaemon, ConnectionError) as exc:
        return fail("replay", str(exc), 3)
    try:
        time.sleep(args.wait)
        stats = replay(bus, args.file, args.rate, args.topics, args.start, args.end)
    except (RecordingError, ValueError) as exc:
        return fail("replay", str(exc))
    finally:
        bus.close()
    print(f"replayed {stats.messages} messages ({stats.bytes / 1e6:.1f} MB) of {args.file} "
          f"on cell {cell!r} in {stats.seconds:.1f} s")
    return 0
