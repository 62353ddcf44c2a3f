"""A Foxglove WebSocket server (ws-protocol v1, the server side scancell needs) on the
``websockets`` library.

Why not foxglove-sdk's server, which the monitor used before: it accepts only the subprotocol
``foxglove.sdk.v1`` and answers HTTP 400 to ``foxglove.websocket.v1``, the subprotocol of
``@foxglove/ws-protocol`` that older Foxglove and Lichtblick builds and every tool built on that
package offer; and it cannot send one client a channel's last message when that client
subscribes. This server speaks v1 under either name and latches every channel.

What it does: Server Info and the channels (Advertise) on connect, Advertise/Unadvertise as
channels come and go, Subscribe/Unsubscribe, Message Data (opcode 1: uint32 subscription id,
uint64 log time in ns, payload; little-endian). A new subscription first gets the channel's
last message. Each client has a bounded queue; when a slow client's queue is full, its oldest
message is dropped, never anybody else's.
"""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
MESSAGE_DATA = 1


@dataclass
class ServerChannel:
    id: int
    topic: str
    encoding: str  # "protobuf" | "json"
    schema_name: str
    schema: bytes  # FileDescriptorSet (protobuf) or JSON Schema text (json)
    last: tuple[int, bytes] | None = None  # (log time ns, payload)

    def advertisement(self) -> dict[str, Any]:
        binary = self.encoding == "protobuf"
        return {"id": self.id, "topic": self.topic, "encoding": self.encoding,
                "schemaName": self.schema_name,
                "schema": base64.b64encode(self.schema).decode() if binary
                else self.schema.decode(),
                "schemaEncoding": "protobuf" if binary else "jsonschema"}


@dataclass(eq=False)  # one per connection, kept in a set
class _Client:
    ws: Any
    queue: asyncio.Queue = field(default_factory=lambda: asyncio.Queue())
    subscriptions: dict[int, int] = field(default_factory=dict)  # subscription id -> channel
    dropped: int = 0


class FoxgloveServer:
    """Start with :meth:`start` (a thread with its own event loop); thread-safe
    :meth:`add_channel` and :meth:`log`; :meth:`stop`."""

    def __init__(self, name: str, host: str = "127.0.0.1", port: int = 8765,
                 backlog: int = 1024) -> None:
        self.name, self.host, self.port, self.backlog = name, host, port, backlog
        self.channels: dict[int, ServerChannel] = {}
        self._by_topic: dict[str, int] = {}
        self._clients: set[_Client] = set()
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Any = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, daemon=True, name="foxglove-server")
        self._session = str(time.time_ns())

    # ---------------------------------------------------------------- control (any thread)
    def start(self, timeout_s: float = 10.0) -> None:
        """Listen; raises OSError if the address cannot be served (port taken)."""
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise OSError(f"the Foxglove server on {self.host}:{self.port} did not start")
        if self._error is not None:
            raise OSError(f"cannot serve on {self.host}:{self.port}: {self._error}")

    def stop(self) -> None:
        if self._loop is not None and self._thread.is_alive():
            asyncio.run_coroutine_threadsafe(self._shutdown(), self._loop).result(10)
            self._thread.join(5)

    def add_channel(self, topic: str, encoding: str, schema_name: str, schema: bytes) -> int:
        """The channel of ``topic`` (made and advertised to every client if new)."""
        with self._lock:
            if topic in self._by_topic:
                return self._by_topic[topic]
            cid = len(self.channels) + 1
            ch = ServerChannel(cid, topic, encoding, schema_name, schema)
            self.channels[cid] = ch
            self._by_topic[topic] = cid
        self._call(self._broadcast, {"op": "advertise", "channels": [ch.advertisement()]})
        return cid

    def log(self, channel_id: int, payload: bytes, log_time_ns: int) -> None:
        """Send to every subscriber, and keep it as the channel's last message."""
        with self._lock:
            self.channels[channel_id].last = (log_time_ns, payload)
        self._call(self._send_data, channel_id, payload, log_time_ns)

    # ---------------------------------------------------------------- event loop
    def _call(self, fn, *args) -> None:
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(fn, *args)

    def _main(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:  # reported to start()
            self._error = exc
            self._ready.set()

    async def _serve(self) -> None:
        from websockets.asyncio.server import serve

        self._loop = asyncio.get_running_loop()
        self._stopped = asyncio.Event()
        async with serve(self._client, self.host, self.port, max_size=None, compression=None,
                         subprotocols=list(SUBPROTOCOLS)) as server:
            self._server = server
            self.port = server.sockets[0].getsockname()[1]
            self._ready.set()
            await self._stopped.wait()

    async def _shutdown(self) -> None:
        for c in list(self._clients):
            await c.ws.close()
        self._stopped.set()

    async def _client(self, ws: Any) -> None:
        client = _Client(ws)
        with self._lock:
            self._clients.add(client)
            channels = [c.advertisement() for c in self.channels.values()]
        writer = asyncio.create_task(self._writer(client))
        try:
            await ws.send(json.dumps({"op": "serverInfo", "name": self.name, "capabilities": [],
                                      "metadata": {}, "sessionId": self._session}))
            await ws.send(json.dumps({"op": "advertise", "channels": channels}))
            async for raw in ws:
                if isinstance(raw, str):
                    self._on_request(client, raw)
        except Exception as exc:  # a client that breaks the protocol or the connection
            log.info("foxglove client %s: %s", ws.remote_address, exc)
        finally:
            writer.cancel()
            with self._lock:
                self._clients.discard(client)

    def _on_request(self, client: _Client, raw: str) -> None:
        try:
            msg = json.loads(raw)
            op = msg["op"]
            if op == "subscribe":
                for sub in msg["subscriptions"]:
                    sid, cid = int(sub["id"]), int(sub["channelId"])
                    with self._lock:
                        ch = self.channels.get(cid)
                        if ch is None or sid in client.subscriptions:
                            raise ValueError(f"subscription {sid}: unknown channel {cid} or "
                                             f"id in use")
                        client.subscriptions[sid] = cid
                        last = ch.last
                    if last is not None:  # latched: the new subscriber gets the last message
                        self._enqueue(client, _frame(sid, *last))
            elif op == "unsubscribe":
                for sid in msg["subscriptionIds"]:
                    client.subscriptions.pop(int(sid), None)
        except (ValueError, KeyError, TypeError) as exc:
            self._enqueue(client, json.dumps({"op": "status", "level": 2,
                                              "message": f"bad request: {exc}"}))

    def _broadcast(self, message: dict[str, Any]) -> None:
        text = json.dumps(message)
        for c in list(self._clients):
            self._enqueue(c, text)

    def _send_data(self, channel_id: int, payload: bytes, log_time_ns: int) -> None:
        for c in list(self._clients):
            for sid, cid in list(c.subscriptions.items()):
                if cid == channel_id:
                    self._enqueue(c, _frame(sid, log_time_ns, payload))

    def _enqueue(self, client: _Client, item: str | bytes) -> None:
        if client.queue.qsize() >= self.backlog:
            client.queue.get_nowait()  # a slow client loses its oldest message
            client.dropped += 1
        client.queue.put_nowait(item)

    @staticmethod
    async def _writer(client: _Client) -> None:
        while True:
            await client.ws.send(await client.queue.get())


def _frame(subscription_id: int, log_time_ns: int, payload: bytes) -> bytes:
    return struct.pack("<BIQ", MESSAGE_DATA, subscription_id, log_time_ns) + payload
