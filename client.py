"""The cell controller's side: call daemon commands over zenoh.

    from scancell.client import CellClient
    with CellClient("sim") as cell:
        print(cell.status())
        cell.call("device/robot/move_joints", {"joints_deg": [0, 0, 0, 0, -90, 0]})

``await cell.acall(...)`` does the same from asyncio code.
"""

from __future__ import annotations

import asyncio
from typing import Any

from scancell.bus import Bus, BusConfig, NoDaemon
from scancell.protocols.commands import CommandError
from scancell.protocols.keys import DEFAULT_CELL

__all__ = ["CellClient", "CommandError", "NoDaemon"]


class CellClient:
    """A zenoh session bound to one cell's command keys."""

    def __init__(self, cell: str = DEFAULT_CELL, connect: str | list[str] | None = None,
                 bus_config: BusConfig | None = None, timeout_s: float = 130.0,
                 connect_wait_s: float = 3.0) -> None:
        self.cell = cell
        self.bus_config = bus_config or BusConfig.client_default(connect)
        self.timeout_s = timeout_s
        self.connect_wait_s = connect_wait_s
        self._bus: Bus | None = None

    @property
    def bus(self) -> Bus:
        """The zenoh session, opened on first use (raises NoDaemon if the daemon is not up)."""
        if self._bus is None:
            self._bus = Bus.open(self.bus_config, self.cell, self.connect_wait_s)
        return self._bus

    def call(self, verb: str, request: dict[str, Any] | None = None,
             timeout_s: float | None = None) -> Any:
        """Return the command's result; raise CommandError (error reply) or NoDaemon."""
        return self.bus.call(verb, request, timeout_s or self.timeout_s)

    async def acall(self, verb: str, request: dict[str, Any] | None = None,
                    timeout_s: float | None = None) -> Any:
        return await asyncio.to_thread(self.call, verb, request, timeout_s)

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def devices(self) -> list[dict[str, Any]]:
        return self.call("devices")["devices"]

    def alive(self) -> list[str]:
        return self.bus.alive()

    def close(self) -> None:
        if self._bus is not None:
            self._bus.close()
            self._bus = None

    def __enter__(self) -> CellClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
