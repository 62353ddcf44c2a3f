"""Where a DLPC controller's 64-byte HID reports go: a USB HID device or a TCP socket.

The transport knows nothing of the protocol (``protocols/dlp_hid.py``): it moves reports.

- ``hid://VID:PID[/serial]`` (hex VID and PID, e.g. ``hid://0451:6401``): the device through
  hidapi (the ``hid`` module of the ``hidapi`` package); hidapi's leading report-ID byte (0) is
  added on write.
- ``socket://host:port``: the emulator (``scancell sim serve projector``) or any bridge; each
  report is its 64 bytes, back to back.
"""

from __future__ import annotations

import contextlib
import select
import socket
from typing import Protocol
from urllib.parse import urlparse

from scancell.devices.errors import ConnectionLost, Timeout
from scancell.protocols.dlp_hid import REPORT_SIZE


class HidLink(Protocol):
    """A blocking report link (drivers call it from a worker thread)."""

    def write(self, report: bytes) -> None: ...

    def read(self, timeout_s: float) -> bytes:
        """One 64-byte report; Timeout if none arrives, ConnectionLost if the link is gone."""
        ...

    def close(self) -> None: ...


class SocketLink:
    def __init__(self, host: str, port: int, timeout_s: float = 2.0) -> None:
        self.where = f"socket://{host}:{port}"
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise ConnectionLost(f"cannot connect to {self.where}: {exc}") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buf = b""

    def write(self, report: bytes) -> None:
        try:
            self._sock.sendall(report)
        except OSError as exc:
            raise ConnectionLost(f"{self.where}: write failed: {exc}") from None

    def read(self, timeout_s: float) -> bytes:
        while len(self._buf) < REPORT_SIZE:
            try:
                ready, _, _ = select.select([self._sock], [], [], timeout_s)
                if not ready:
                    raise Timeout(f"{self.where}: no reply within {timeout_s} s")
                chunk = self._sock.recv(4096)
            except OSError as exc:
                raise ConnectionLost(f"{self.where}: read failed: {exc}") from None
            if not chunk:
                raise ConnectionLost(f"{self.where}: the controller closed the connection")
            self._buf += chunk
        report, self._buf = self._buf[:REPORT_SIZE], self._buf[REPORT_SIZE:]
        return report

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.close()


class UsbHidLink:
    def __init__(self, vid: int, pid: int, serial: str | None) -> None:
        self.where = f"hid://{vid:04x}:{pid:04x}" + (f"/{serial}" if serial else "")
        try:
            import hid
        except ImportError as exc:
            raise ConnectionLost(f"{self.where}: the hidapi package is not installed ({exc})") \
                from None
        self._dev = hid.device()
        try:
            self._dev.open(vid, pid, serial)
        except (OSError, ValueError) as exc:
            raise ConnectionLost(f"cannot open {self.where}: {exc} (is it plugged in, and may "
                                 f"this user open it? see docs/tutorials/first-real-cell.md)") from None

    def write(self, report: bytes) -> None:
        try:
            n = self._dev.write(b"\0" + bytes(report))
        except (OSError, ValueError) as exc:
            raise ConnectionLost(f"{self.where}: write failed: {exc}") from None
        if n < 0:
            raise ConnectionLost(f"{self.where}: write failed (device unplugged?)")

    def read(self, timeout_s: float) -> bytes:
        try:
            data = self._dev.read(REPORT_SIZE, int(timeout_s * 1000))
        except (OSError, ValueError) as exc:
            raise ConnectionLost(f"{self.where}: read failed: {exc}") from None
        if not data:
            raise Timeout(f"{self.where}: no reply within {timeout_s} s")
        return bytes(data).ljust(REPORT_SIZE, b"\0")

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._dev.close()


def open_link(url: str, timeout_s: float = 2.0) -> HidLink:
    """Open ``hid://VID:PID[/serial]`` or ``socket://host:port``; ConnectionLost if it cannot."""
    u = urlparse(url)
    if u.scheme == "socket":
        if not u.hostname or not u.port:
            raise ConnectionLost(f"{url!r}: expected socket://host:port")
        return SocketLink(u.hostname, u.port, timeout_s)
    if u.scheme == "hid":
        try:
            vid_s, pid_s = u.netloc.split(":")
            vid, pid = int(vid_s, 16), int(pid_s, 16)
        except ValueError:
            raise ConnectionLost(f"{url!r}: expected hid://VID:PID[/serial] in hex, e.g. "
                                 f"hid://0451:6401") from None
        return UsbHidLink(vid, pid, u.path.strip("/") or None)
    raise ConnectionLost(f"{url!r}: unknown scheme {u.scheme!r} (hid:// or socket://)")
