"""What the command modules share: the bus and cell arguments, the one default cell, serving a
worker until a signal, and failing with a message.

Like zenoh-python's ``examples/common``: every bus client takes ``--cell`` and ``--connect`` the
same way, with ``$SCANCELL_CELL`` and ``$SCANCELL_CONNECT`` as defaults.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any, Protocol

from scancell.protocols.keys import DEFAULT_CELL

ENV_CELL = "SCANCELL_CELL"


def default_cell_config():
    """The packaged config of the default cell (``deploy/cells/sim.toml``)."""
    from scancell.deploy import cell_config_path

    return cell_config_path(DEFAULT_CELL)


def add_bus_arguments(p: argparse.ArgumentParser) -> None:
    """``--cell``, ``--connect`` and, for a secured cell, ``--user``, ``--password-file``,
    ``--ca`` and ``--bus-config`` (each with its environment variable)."""
    p.add_argument("--cell", default=None,
                   help=f"cell name (default: ${ENV_CELL} or {DEFAULT_CELL!r})")
    p.add_argument("--connect", default=None,
                   help="zenoh endpoint(s) of the daemon or the router, comma-separated, e.g. "
                        "tls/router:7447 (default: $SCANCELL_CONNECT or tcp/127.0.0.1:7447)")
    p.add_argument("--user", default=None,
                   help="user name on a secured router (default: $SCANCELL_USER)")
    p.add_argument("--password-file", default=None, metavar="FILE",
                   help="file holding the user's password (default: $SCANCELL_PASSWORD_FILE, "
                        "or the password itself in $SCANCELL_PASSWORD)")
    p.add_argument("--ca", default=None, metavar="CA.pem",
                   help="CA certificate a TLS router's certificate is checked against "
                        "(default: $SCANCELL_CA)")
    p.add_argument("--bus-config", default=None, metavar="FILE.toml",
                   help="client bus settings as a [bus] table, as in a cell config "
                        "(default: $SCANCELL_BUS_CONFIG); the options above override it")


def bus_config(args: argparse.Namespace):
    """The client ``BusConfig`` the bus arguments and the environment give; raises
    ValueError naming what is wrong."""
    from scancell.bus import BusConfig

    return BusConfig.for_client(args.connect, getattr(args, "user", None),
                                getattr(args, "password_file", None), getattr(args, "ca", None),
                                getattr(args, "bus_config", None))


def cell_name(args: argparse.Namespace) -> str:
    """``--cell``, else ``$SCANCELL_CELL``, else the default cell."""
    return getattr(args, "cell", None) or os.environ.get(ENV_CELL) or DEFAULT_CELL


def add_cluster_arguments(p: argparse.ArgumentParser, scheduler_help: str,
                          metavar: str = "tcp://HOST:PORT|local") -> None:
    """``--scheduler`` (what runs on the Dask cluster: ``scheduler_help``) and ``--workers``
    (the local cluster's size), as every batch command takes them."""
    p.add_argument("--scheduler", default=None, metavar=metavar, help=scheduler_help)
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes of the local cluster (default: one per core)")


def add_decision_arguments(p: argparse.ArgumentParser) -> None:
    """``--decision-rule`` and ``--point-sigma``, as every command that gives verdicts takes
    them (analysis/decision.py)."""
    p.add_argument("--decision-rule", choices=["iso14253-1", "simple"], default=None,
                   help="how a verdict accounts for the uncertainty U (k = 2): iso14253-1, "
                        "pass only inside the tolerance less U, fail beyond it plus U, else "
                        "'not provable' (the default); simple, the tolerance's edge alone")
    p.add_argument("--point-sigma", type=float, default=None, metavar="MM",
                   help="each point's 1-sigma (mm) where the cloud carries no 'uncertainty' "
                        "(default: the cloud's own scatter about local planes, noise only)")


def fail(command: str, message: str, code: int = 2) -> int:
    """Print ``scancell <command>: <message>`` to stderr and return the exit code."""
    print(f"scancell {command}: {message}", file=sys.stderr)
    return code


class Worker(Protocol):
    def start(self) -> None: ...

    def stop(self) -> None: ...


def stop_on_signals() -> threading.Event:
    """An event SIGINT and SIGTERM set (handlers installed now, from the main thread)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def wait_for(stop: threading.Event) -> None:
    """Block the main thread until ``stop`` is set, waking every 0.2 s: a signal the kernel
    delivers to one of zenoh's native threads only flags Python's handler, which runs once the
    main thread executes bytecode again; a bare ``Event.wait()`` then never returns."""
    while not stop.wait(0.2):
        pass


def serve(args: argparse.Namespace, name: str, make: Callable[[Any], Worker],
          banner: Callable[[Any], str], finish: Callable[[Any], None] | None = None) -> int:
    """Open the bus as a client of the daemon, start the worker, print a banner and run until
    SIGINT/SIGTERM; then stop and close. ``name`` as in ``scancell <name>``. Exit 3 if no
    daemon answers within 30 s, 2 if the worker cannot start, else 0 after a signal
    (``finish(worker)`` runs after it stopped)."""
    from scancell.bus import Bus, NoDaemon

    try:
        bus = Bus.open(bus_config(args), cell_name(args), wait_s=30.0)
    except ValueError as exc:
        return fail(name, str(exc))
    except NoDaemon as exc:
        return fail(name, str(exc), 3)
    worker = make(bus)
    stop = stop_on_signals()
    try:
        worker.start()
    except OSError as exc:
        bus.close()
        return fail(name, f"cannot start: {exc}")
    print(banner(bus), flush=True)
    wait_for(stop)
    worker.stop()
    bus.close()
    if finish is not None:
        finish(worker)
    return 0


def table(rows: list[list[Any]], header: list[str]) -> str:
    """Rows as a plain-text table with a header and a rule under it."""
    cells = [[str(c) for c in r] for r in [header, *rows]]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
             for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)
