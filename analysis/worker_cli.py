"""What every bus-client process (``scancell worker …``, ``record``, ``monitor``) does around its
worker: open the bus as a client of the daemon, start, print a banner, run until SIGINT/SIGTERM,
stop and close."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any, Protocol


class Worker(Protocol):
    def start(self) -> None: ...

    def stop(self) -> None: ...


def serve(args: argparse.Namespace, name: str, make: Callable[[Any], Worker],
          banner: Callable[[Any], str], finish: Callable[[Any], None] | None = None) -> int:
    """``name`` as in ``scancell <name>``. Exit 3 if no daemon answers within 30 s, 2 if the
    worker cannot start, else 0 after a signal (``finish(worker)`` runs after it stopped)."""
    from scancell.bus import Bus, BusConfig, NoDaemon

    try:
        bus = Bus.open(BusConfig.client_default(args.connect),
                       args.cell or os.environ.get("SCANCELL_CELL", "sim"), wait_s=30.0)
    except NoDaemon as exc:
        print(f"scancell {name}: {exc}", file=sys.stderr)
        return 3
    worker = make(bus)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        worker.start()
    except OSError as exc:
        print(f"scancell {name}: cannot start: {exc}", file=sys.stderr)
        bus.close()
        return 2
    print(banner(bus), flush=True)
    stop.wait()
    worker.stop()
    bus.close()
    if finish is not None:
        finish(worker)
    return 0
