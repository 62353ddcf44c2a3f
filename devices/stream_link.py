"""A device's byte stream opened through ``serial.serial_for_url`` (``socket://host:port``, a
serial port or pseudo-terminal, ``loop://``), read by its own thread.

What arrives goes to the driver's ``on_bytes``; the first time the link breaks (the device
closed it, the port vanished, or ``on_bytes`` raised :class:`LinkBroken` because the stream
can no longer be read) the driver's ``on_lost`` hears why, once. After that, and before
:meth:`open`, :meth:`write` raises ConnectionLost.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable
from typing import Any

import serial
from scancell.devices.byte_stream import READ_WAIT_S, read_available
from scancell.devices.errors import ConnectionLost


class LinkBroken(Exception):
    """Raised by ``on_bytes``: the stream cannot be read on (the message says why)."""


class StreamLink:
    def __init__(self, name: str, url: str, on_bytes: Callable[[bytes], None],
                 on_lost: Callable[[str], None], **serial_options: Any) -> None:
        self.name, self.url = name, url
        self.on_bytes, self.on_lost = on_bytes, on_lost
        self.serial_options = serial_options
        self._port: serial.SerialBase | None = None
        self._reader: threading.Thread | None = None
        self._closing = threading.Event()
        #: why the link broke, or None while it is up (and before it was opened)
        self.error: str | None = None

    @property
    def is_open(self) -> bool:
        return self._port is not None and self.error is None

    async def open(self) -> None:
        """Open the URL and start reading; ConnectionLost naming the URL if it cannot."""
        await self.close()
        self._closing.clear()
        self.error = None
        try:
            self._port = await asyncio.to_thread(serial.serial_for_url, self.url,
                                                 timeout=READ_WAIT_S, **self.serial_options)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ConnectionLost(f"{self.name}: cannot open {self.url}: {exc}") from None
        self._reader = threading.Thread(target=self._read, daemon=True, name=f"{self.name}-rx")
        self._reader.start()

    async def close(self) -> None:
        self._closing.set()
        if self._port is not None:
            with contextlib.suppress(Exception):
                self._port.close()
        if self._reader is not None:
            await asyncio.to_thread(self._reader.join, 1.0)
        self._port = self._reader = None

    async def write(self, data: bytes) -> None:
        if self._port is None or self.error:
            raise ConnectionLost(f"{self.name}: {self.error or 'not connected'}")
        try:
            await asyncio.to_thread(self._port.write, data)
        except (serial.SerialException, OSError) as exc:
            raise ConnectionLost(f"{self.name}: write failed: {exc}") from None

    def _lost(self, reason: str) -> None:
        if not self._closing.is_set() and self.error is None:
            self.error = reason
            self.on_lost(reason)

    def _read(self) -> None:
        port = self._port
        try:
            while not self._closing.is_set() and port is not None:
                data = read_available(port)
                if data:
                    self.on_bytes(data)
        except LinkBroken as exc:
            self._lost(str(exc))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            self._lost(f"link lost: {exc}")
