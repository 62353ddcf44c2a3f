"""``scancell opcua``: serve one cell on OPC UA for a line's PLC or MES (docs/how-to/opcua.md)."""

from __future__ import annotations

import argparse
import asyncio

from scancell.cli._common import add_bus_arguments, bus_config, cell_name, fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_bus_arguments(p)
    p.add_argument("--endpoint", default="opc.tcp://0.0.0.0:4840/scancell/",
                   help="the OPC UA endpoint to serve (default opc.tcp://0.0.0.0:4840/scancell/)")
    p.add_argument("--users", required=True, metavar="USERS.toml",
                   help="[users.<name>] role = controller|engineer|monitor, password_sha256")
    p.add_argument("--plans", required=True, metavar="DIR",
                   help="the stored plans StartJob names (DIR/<name>.toml)")
    p.add_argument("--anonymous", choices=("monitor", "refused"), default="monitor",
                   help="what an anonymous session may do (default: read, as monitor)")


def main(args: argparse.Namespace) -> int:
    from pathlib import Path

    from scancell.bus import NoDaemon
    from scancell.cli._common import stop_on_signals
    from scancell.client import CellClient
    from scancell.gateways.opcua import GatewayError, OpcUaGateway, load_users

    try:
        users = load_users(args.users)
        if not Path(args.plans).is_dir():
            raise GatewayError(f"--plans {args.plans}: not a folder")
        client = CellClient(cell_name(args), bus_config=bus_config(args), connect_wait_s=30.0)
        client.bus  # noqa: B018  (opens the session: fails now if no daemon answers)
    except (GatewayError, ValueError) as exc:
        return fail("opcua", str(exc))
    except NoDaemon as exc:
        return fail("opcua", str(exc), 3)
    stop = stop_on_signals()

    async def run() -> int:
        gateway = OpcUaGateway(client, args.endpoint, users, args.plans,
                               None if args.anonymous == "refused" else "monitor")
        try:
            await gateway.start()
        except OSError as exc:
            return fail("opcua", f"cannot serve {args.endpoint}: {exc}")
        print(f"OPC UA server for cell {client.cell!r} on {args.endpoint} ({len(users)} users; "
              f"plans {', '.join(gateway.plans()) or 'none'})", flush=True)
        while not stop.is_set():
            await asyncio.sleep(0.2)
        await gateway.stop()
        return 0

    try:
        return asyncio.run(run())
    finally:
        client.close()
