"""What the simulators' TCP servers share: the listening socket, the clients' writers, a
periodic tick for what a device sends on its own (events, streams), and closing."""

from __future__ import annotations

import asyncio
import contextlib


class TcpService:
    """Serve ``_serve(reader, writer)`` per client on ``host:port`` (0: a free port), and call
    ``_tick()`` in a loop: it sends what the device sends unasked and returns the seconds to
    its next call."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self.host, self._port = host, port
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._ticker: asyncio.Task | None = None

    @property
    def port(self) -> int:
        return self._server.sockets[0].getsockname()[1] if self._server else self._port

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._client, self.host, self._port)
        self._ticker = asyncio.create_task(self._tick_loop())

    async def close(self) -> None:
        if self._ticker:
            self._ticker.cancel()
        if self._server:
            self._server.close()
        self.drop_clients()
        if self._server:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(1.0):
                    await self._server.wait_closed()

    def drop_clients(self) -> None:
        """Close every client's connection (a cable pulled, a server restarted)."""
        for w in list(self._writers):
            w.close()

    def broadcast(self, chunks: list[bytes]) -> None:
        """Write ``chunks`` to every client."""
        for w in list(self._writers):
            for c in chunks:
                w.write(c)

    async def _tick(self) -> float:
        return 1.0

    async def _tick_loop(self) -> None:
        while True:
            await asyncio.sleep(await self._tick())

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        raise NotImplementedError

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        try:
            await self._serve(reader, writer)
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self._writers.discard(writer)
            writer.close()
