"""What the DLPC350 and DLPC900 drivers share: the report link, transactions, status, playing.

A driver programs the controller's pattern LUT for a sequence spec and validates it; then
:meth:`play` runs the sequence once (each pattern pulses trigger out 1 to the cameras) and
:meth:`show` displays one pattern (a one-entry LUT, after which :meth:`play` programs the whole
sequence again). Transactions run in a worker thread, one at a time; a reply's sequence byte
must echo the request's.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from abc import abstractmethod
from typing import Any, ClassVar

from scancell.devices.base import OK, Health, HealthState, Projector
from scancell.devices.errors import BadReply, ConnectionLost, DeviceFault, Timeout
from scancell.devices.hid_link import HidLink, open_link
from scancell.protocols import dlp_hid
from scancell.protocols.commands import CommandError

log = logging.getLogger(__name__)

DLP_OPTIONS: dict[str, Any] = {
    "url": {"type": "string"},
    "timeout_s": {"type": "number", "exclusiveMinimum": 0},
    "exposure_us": {"type": "integer", "minimum": 1},
    "trigger_out_invert": {"type": "boolean"},
}


class ValidationFailed(CommandError):
    """The controller refused a pattern sequence; the message names the rule broken."""

    def __init__(self, message: str) -> None:
        super().__init__("invalid", message)


class DlpProjector(Projector):
    """Base of the LightCrafter drivers (subclasses: the controller's command set)."""

    plays_sequences = True
    names: ClassVar[dict[int, str]] = {}

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self.url = str(self.options.get("url", ""))
        self.timeout_s = float(self.options.get("timeout_s", 2.0))
        self._link: HidLink | None = None
        self._lock = threading.Lock()
        self._seq = 0
        self.versions: dict[str, str] = {}
        self.patterns = 0
        self._full = False  # the controller holds the whole loaded sequence (not one pattern)

    # ---------------------------------------------------------------- link
    async def connect(self) -> None:
        await self.close()
        self._link = await asyncio.to_thread(open_link, self.url, self.timeout_s)
        try:
            data = await self.read(dlp_hid.GET_VERSION, min_bytes=16)
            self.versions = {k: str(v) for k, v in dlp_hid.read_versions(data).items()}
            await self._on_connect()
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            await asyncio.to_thread(link.close)

    @abstractmethod
    async def _on_connect(self) -> None:
        """Leave standby, enter pattern mode (the versions are read)."""

    def _transact(self, req: dlp_hid.Request) -> dlp_hid.Reply | None:
        link = self._link
        if link is None:
            raise ConnectionLost(f"{self.name}: not connected")
        with self._lock:
            self._seq = (self._seq + 1) & 0xFF
            req = dlp_hid.Request(req.command, req.data, req.read, req.reply, self._seq)
            what = f"{self.name}: {dlp_hid.command_name(self.names, req.command)}"
            try:
                for report in dlp_hid.to_reports(dlp_hid.encode_request(req)):
                    link.write(report)
                if not req.reply:
                    return None
                while True:
                    first = link.read(self.timeout_s)
                    reports = [first] + [link.read(self.timeout_s)
                                         for _ in range(dlp_hid.reports_needed(first) - 1)]
                    reply = dlp_hid.decode_reply(dlp_hid.join_reports(reports))
                    if reply.seq == req.seq:
                        return reply
                    log.warning("%s: dropped a stale reply (sequence %d, expected %d)", what,
                                reply.seq, req.seq)
            except dlp_hid.HidFrameError as exc:
                self._drain(link)
                raise BadReply(f"{what}: {exc}") from None
            except Timeout as exc:
                raise Timeout(f"{what}: {exc}") from None

    @staticmethod
    def _drain(link: HidLink) -> None:
        """Drop whatever the controller still sends after a garbled reply, so the next
        transaction starts on a report boundary."""
        try:
            while True:
                link.read(0.05)
        except Timeout:
            pass

    async def write(self, command: int, data: bytes = b"", check: bool = True) -> None:
        """Write ``command``; the controller's error flag raises unless ``check`` is False."""
        reply = await asyncio.to_thread(self._transact, dlp_hid.Request(command, data))
        if check and reply is not None and reply.error:
            raise await self._command_failed(command)

    async def read(self, command: int, data: bytes = b"", min_bytes: int = 1) -> bytes:
        reply = await asyncio.to_thread(self._transact,
                                        dlp_hid.Request(command, data, read=True))
        assert reply is not None
        if reply.error:
            raise await self._command_failed(command)
        if len(reply.data) < min_bytes:
            raise BadReply(f"{self.name}: {dlp_hid.command_name(self.names, command)} answered "
                           f"{len(reply.data)} bytes, expected ≥ {min_bytes}")
        return reply.data

    async def _command_failed(self, command: int) -> Exception:
        return DeviceFault(f"{self.name}: the controller refused "
                           f"{dlp_hid.command_name(self.names, command)} (error flag set)")

    # ---------------------------------------------------------------- status
    @abstractmethod
    async def _faults(self) -> list[str]:
        """The faults the status registers report."""

    async def health(self) -> Health:
        faults = await self._faults()
        if faults:
            return Health(HealthState.FAULT, "controller_fault", "; ".join(faults))
        return OK

    # ---------------------------------------------------------------- patterns
    def _exposure_us(self, spec: dict[str, Any], minimum: int) -> int:
        """The pattern exposure: the driver's option, raised to the spec's ``display_us`` (the
        cameras' exposure) and to the controller's minimum for the bit depth."""
        return max(int(self.options.get("exposure_us", 0)), int(spec.get("display_us", 0)),
                   minimum)

    async def show(self, index: int) -> None:
        if index < 0:
            await self._start_stop(dlp_hid.STOP)
            return
        if not 0 <= index < self.patterns:
            raise CommandError("out_of_range", f"{self.name}: pattern {index} outside the "
                                               f"loaded sequence of {self.patterns}")
        await self._start_stop(dlp_hid.STOP)
        await self._program_one(index)
        self._full = False
        await self._start_stop(dlp_hid.START)

    async def play(self) -> None:
        if not self._full:
            await self._start_stop(dlp_hid.STOP)
            await self._program_all()
            self._full = True
        await self._start_stop(dlp_hid.START)

    async def _start_stop(self, action: int) -> None:
        await self.write(dlp_hid.PAT_START_STOP, bytes([action]))

    @abstractmethod
    async def _program_all(self) -> None:
        """Program the loaded sequence to play once (the sequence is stopped)."""

    @abstractmethod
    async def _program_one(self, index: int) -> None:
        """Program pattern ``index`` alone, held until the next command (stopped)."""
