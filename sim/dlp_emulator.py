"""Emulators of TI's DLPC350 and DLPC900 controllers on TCP (64-byte HID reports, back to back).

Each keeps the controller's state, enforces its rules (the DLPC350's Validate Data bits, the
DLPC900's error codes) and answers with the same reports. Playing a sequence displays its
patterns on a :class:`Display` (the simulated cell's, ``sim/projector_images.py``) and pulses
trigger out once per pattern, at the pattern period. Faults for tests: ``drop_reply`` (the next
reply is lost), ``validation`` (the next validation fails with the given bits), ``disconnect``
(every connection is cut).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
import time
from abc import ABC, abstractmethod
from typing import Any, ClassVar, Protocol

import numpy as np
from scancell.model.pattern_set import sequence_pattern_set
from scancell.protocols import dlp_hid
from scancell.protocols import dlpc350 as c350
from scancell.protocols import dlpc900 as c900

log = logging.getLogger(__name__)

#: What the emulated controllers answer to GET_VERSION.
VERSIONS = dlp_hid.pack_versions({
    "application": dlp_hid.Version(3, 0, 0), "api": dlp_hid.Version(2, 0, 0),
    "software_config": dlp_hid.Version(1, 0, 0), "sequence_config": dlp_hid.Version(1, 0, 0)})
#: The flash of ``scancell sim serve projector`` and of deploy/cells/sim.toml: the scanner's
#: fringes (images 0-2), 18 uniform levels (images 3-8).
DEFAULT_FLASH: list[dict[str, Any]] = [
    {"kind": "fringe", "periods": [70, 64, 59], "steps": 3, "first_image": 0},
    {"kind": "levels", "levels": list(range(0, 256, 15)), "first_image": 3},
]


class Display(Protocol):
    def load(self, images: list[np.ndarray]) -> None: ...

    def show(self, i: int) -> None: ...


class NullDisplay:
    def load(self, images: list[np.ndarray]) -> None:
        pass

    def show(self, i: int) -> None:
        pass


class FirmwareError(Exception):
    def __init__(self, message: str, code: int = c900.ERR_INVALID_PARAMETER) -> None:
        super().__init__(message)
        self.code = code


class Firmware(ABC):
    """Common state: power, running sequence, forced validation failure."""

    names: ClassVar[dict[int, str]] = {}
    write_length: ClassVar[dict[int, int | None]] = {}
    readable: ClassVar[set[int]] = set()

    def __init__(self) -> None:
        self.standby = False
        self.running = False
        self.forced_validation = 0
        self.period_s = 0.01
        self.repeat = False

    def handle(self, req: dlp_hid.Request) -> bytes:
        name = dlp_hid.command_name(self.names, req.command)
        if req.read:
            if req.command not in self.readable:
                raise FirmwareError(f"{name} cannot be read", c900.ERR_INVALID_COMMAND)
            return self.read(req.command, req.data)
        if req.command not in self.write_length:
            raise FirmwareError(f"unknown command {name}", c900.ERR_INVALID_COMMAND)
        n = self.write_length[req.command]
        if n is not None and len(req.data) != n:
            raise FirmwareError(f"{name} takes {n} data bytes, got {len(req.data)}")
        self.write(req.command, req.data)
        return b""

    @abstractmethod
    def read(self, command: int, data: bytes) -> bytes:
        """The reply data of a read (FirmwareError if refused)."""

    @abstractmethod
    def write(self, command: int, data: bytes) -> None:
        """Carry out a write (FirmwareError if refused)."""

    @abstractmethod
    def images(self) -> list[np.ndarray]:
        """The 8-bit images of the sequence to play, in LUT order."""


class Dlpc350Firmware(Firmware):
    names = c350.NAMES
    write_length = c350.WRITE_LENGTH
    readable = c350.READABLE

    def __init__(self, flash: list[dict[str, Any]], width: int, height: int) -> None:
        super().__init__()
        self.flash = flash_images(flash, width, height)
        self.mode = 0
        self.source = c350.SOURCE_FLASH
        self.trigger_mode = c350.TRIGGER_INTERNAL
        self.exposure_us, self.period_us = 8333, 8333
        self.config = c350.PatternConfig(1, False, 1, 1)
        self.mailbox = 0
        self.address = 0
        self.lut: list[c350.LutEntry | None] = []  # memory: None where nothing was written
        self.image_lut: list[int | None] = []
        self.status = 0
        self.validated = False
        self.trig_out1 = bytes([0, 0xBB, 0xBB])
        self.trig_out2 = bytes([0, 0xBB])
        self.settings = {cmd: bytes(n) for cmd, n in c350.SETTINGS.items()}

    def read(self, command: int, data: bytes) -> bytes:
        c = c350
        if command == c.GET_VERSION:
            return VERSIONS
        if command == c.FIRMWARE_TAG:
            return b"scancell DLPC350 emulator".ljust(32, b"\0")
        if command == c.STATUS_HW:
            return bytes([c.HW_INIT_DONE])
        if command == c.STATUS_SYS:
            return bytes([c.SYS_MEMORY_TEST_PASSED])
        if command == c.STATUS_MAIN:
            return bytes([c.MAIN_SEQUENCE_RUNNING if self.running else 0])
        if command == c.LUT_VALID:
            return bytes([self.status])
        if command == c.NUM_IMAGE_IN_FLASH:
            return bytes([len(self.flash)])
        simple = {c.POWER_CONTROL: int(self.standby), c.DISP_MODE: self.mode,
                  c.PAT_DISP_MODE: self.source, c.PAT_TRIG_MODE: self.trigger_mode,
                  c.PAT_START_STOP: c.START if self.running else c.STOP,
                  c.SOURCE_SEL: 2, c.LED_ENABLE: 0x08}
        if command in simple:
            return bytes([simple[command]])
        if command == c.PAT_EXPO_PRD:
            return c.exposure_period(self.exposure_us, self.period_us)
        if command == c.PAT_CONFIG:
            return self.config.pack()
        if command == c.TRIG_OUT1_CTL:
            return self.trig_out1
        if command == c.TRIG_OUT2_CTL:
            return self.trig_out2
        if command == c.LED_CURRENT:
            return bytes([0x97, 0x78, 0x7D])
        if command in self.settings:
            return self.settings[command]
        raise FirmwareError(f"{c.NAMES.get(command)} cannot be read")

    def _needs_stop(self, name: str) -> None:
        if self.running:
            raise FirmwareError(f"{name}: stop the pattern sequence first",
                                c900.ERR_NOT_ALLOWED)

    def write(self, command: int, data: bytes) -> None:
        c = c350
        name = dlp_hid.command_name(self.names, command)
        if command == c.POWER_CONTROL:
            self.standby = bool(data[0])
        elif command == c.PAT_START_STOP:
            action = data[0] & 3
            if action == c.START:
                if self.mode != 1 or not self.validated or self.status & (
                        c.VALID_EXPOSURE | c.VALID_PATTERN_NUMBER):
                    raise FirmwareError("start refused: the sequence is not validated",
                                        c900.ERR_NOT_ALLOWED)
                if self.standby:
                    raise FirmwareError("start refused: the controller is in standby",
                                        c900.ERR_NOT_ALLOWED)
                self.period_s = self.period_us * 1e-6
                self.repeat = self.config.repeat
                self.running = True
            else:
                self.running = False
        elif command in (c.DISP_MODE, c.PAT_DISP_MODE, c.PAT_TRIG_MODE, c.PAT_EXPO_PRD,
                         c.PAT_CONFIG, c.TRIG_OUT1_CTL, c.TRIG_OUT2_CTL):
            self._needs_stop(name)
            self.validated = False
            if command == c.DISP_MODE:
                self.mode = data[0] & 1
            elif command == c.PAT_DISP_MODE:
                if data[0] not in (0, c.SOURCE_FLASH):
                    raise FirmwareError(f"{name}: {data[0]} is not 0 (video port) or 3 (flash)")
                self.source = data[0]
            elif command == c.PAT_TRIG_MODE:
                self.trigger_mode = data[0]
            elif command == c.PAT_EXPO_PRD:
                self.exposure_us, self.period_us = c.read_exposure_period(data)
            elif command == c.PAT_CONFIG:
                self.config = c.PatternConfig.unpack(data)
            elif command == c.TRIG_OUT1_CTL:
                self.trig_out1 = data
            else:
                self.trig_out2 = data
        elif command == c.MBOX_CONTROL:
            self._needs_stop(name)
            if data[0] not in (0, c.MAILBOX_IMAGE, c.MAILBOX_PATTERN):
                raise FirmwareError(f"{name}: mailbox {data[0]} is not 0, 1 or 2")
            self.mailbox, self.address = data[0], 0
        elif command == c.MBOX_ADDRESS:
            self.address = data[0]
        elif command == c.MBOX_DATA:
            self._mailbox_data(data)
        elif command == c.LUT_VALID:
            self._needs_stop(name)
            lut, image_lut = self.configured()
            self.status = self.forced_validation or c.validation_status(
                self.exposure_us, self.period_us, lut, image_lut, len(self.flash), self.config,
                self.source)
            self.forced_validation = 0
            self.validated = True
        elif command in self.settings:
            self.settings[command] = data
        elif command in (c.LED_CURRENT, c.SOURCE_SEL, c.LED_ENABLE, c.SW_RESET):
            pass

    def _mailbox_data(self, data: bytes) -> None:
        # The mailboxes are memory (DLPC350_MailboxSetAddr: an offset 0-127 into a LUT that
        # keeps its other entries); the sequence uses the first PAT_CONFIG entries of each.
        if self.mailbox == c350.MAILBOX_PATTERN:
            try:
                entries = c350.unpack_lut(data)
            except ValueError as exc:
                raise FirmwareError(f"MBOX_DATA: {exc}") from None
            self._store(self.lut, entries, c350.LUT_ENTRIES, "pattern LUT")
        elif self.mailbox == c350.MAILBOX_IMAGE:
            lut = list(data[::-1] if len(data) == 2 else data)  # the API's 2-entry swap
            self._store(self.image_lut, lut, c350.LUT_ENTRIES, "image LUT")
        else:
            raise FirmwareError("MBOX_DATA: no mailbox is open (MBOX_CONTROL 1 or 2 first)",
                                c900.ERR_NOT_ALLOWED)
        self.validated = False

    def _store(self, memory: list, values: list, size: int, what: str) -> None:
        end = self.address + len(values)
        if end > size:
            raise FirmwareError(f"MBOX_DATA: {len(values)} entries at offset {self.address} pass "
                                f"the {what}'s {size}")
        if len(memory) < end:
            memory.extend([None] * (end - len(memory)))
        memory[self.address:end] = values

    def configured(self) -> tuple[list[c350.LutEntry | None], list[int | None]]:
        """The pattern and image LUT entries the sequence uses (PAT_CONFIG's counts)."""
        return self.lut[:self.config.entries], self.image_lut[:self.config.images]

    def images(self) -> list[np.ndarray]:
        if self.source != c350.SOURCE_FLASH:
            return []  # the video port: no signal reaches an emulator
        out, image = [], -1
        lut, image_lut = self.configured()
        for e in lut:
            if e.buffer_swap:
                image += 1
            planes = self.flash[image_lut[image]]
            out.append(planes[e.pattern])
        return out


class Dlpc900Firmware(Firmware):
    names = c900.NAMES
    write_length = c900.WRITE_LENGTH
    readable = c900.READABLE

    def __init__(self, width: int, height: int) -> None:
        super().__init__()
        self.width, self.height = width, height
        self.mode = c900.MODE_VIDEO
        self.definitions: dict[int, c900.LutDefinition] = {}
        self.entries = 0
        self.patterns = 0
        self.uploaded: dict[int, np.ndarray] = {}
        self.upload: tuple[int, int, bytearray] | None = None
        self.error = (0, "")
        self.curtain = bytes(6)
        self.idle = False  # DMD_IDLE: the mirrors at a 50 % duty cycle, nothing shown
        self.trig_out1 = bytes(5)
        self.trig_out2 = bytes(5)

    def handle(self, req: dlp_hid.Request) -> bytes:
        try:
            out = super().handle(req)
        except FirmwareError as exc:
            self.error = (exc.code, str(exc))
            raise
        if not (req.read and req.command in (c900.READ_ERROR_CODE,
                                             c900.READ_ERROR_DESCRIPTION)):
            self.error = (0, "")
        return out

    def read(self, command: int, data: bytes) -> bytes:
        c = c900
        if command == c.READ_ERROR_CODE:
            return bytes([self.error[0]])
        if command == c.READ_ERROR_DESCRIPTION:
            return self.error[1].encode("ascii", "replace")[:127] + b"\0"
        if command == c.GET_VERSION:
            return VERSIONS
        if command == c.STATUS_HW:
            return bytes([c.HW_INIT_DONE])
        if command == c.STATUS_SYS:
            return b"\x01"
        if command == c.STATUS_MAIN:
            return bytes([c.MAIN_SEQUENCE_RUNNING if self.running else 0])
        if command == c.POWER_MODE:
            return bytes([int(self.standby)])
        if command == c.DMD_IDLE:
            return bytes([int(self.idle)])
        if command == c.DISP_MODE:
            return bytes([self.mode])
        if command == c.CURTAIN_COLOR:
            return self.curtain
        if command == c.LUT_CONFIG:
            return c.lut_config(max(self.entries, 1), self.patterns)
        if command == c.MIN_EXPOSURE:
            return c.min_exposures()
        if command == c.TRIG_OUT1_CTL:
            return self.trig_out1
        return self.trig_out2

    def write(self, command: int, data: bytes) -> None:
        c = c900
        if command == c.POWER_MODE:
            self.standby = data[0] == 1
        elif command == c.DMD_IDLE:
            if data[0] > 1:
                raise FirmwareError(f"DMD_IDLE {data[0]} is not 0 (normal) or 1 (idle)",
                                    c900.ERR_INVALID_PARAMETER)
            self.idle = data[0] == 1
        elif command == c.CURTAIN_COLOR:
            self.curtain = data
        elif command == c.DISP_MODE:
            if data[0] > 3:
                raise FirmwareError(f"DISP_MODE {data[0]} is not 0 ... 3")
            self.running, self.mode = False, data[0]
        elif command == c.PAT_START_STOP:
            self._start_stop(data[0] & 3)
        elif command in (c.TRIG_OUT1_CTL, c.TRIG_OUT2_CTL):
            if command == c.TRIG_OUT1_CTL:
                self.trig_out1 = data
            else:
                self.trig_out2 = data
        elif self.mode != c.MODE_ON_THE_FLY:
            raise FirmwareError(f"{dlp_hid.command_name(self.names, command)}: only in "
                                f"pattern-on-the-fly mode "
                                f"(DISP_MODE 3)", c.ERR_NOT_ALLOWED)
        elif self.running:
            raise FirmwareError(f"{dlp_hid.command_name(self.names, command)}: stop the pattern "
                                f"sequence first",
                                c.ERR_NOT_ALLOWED)
        elif command == c.LUT_DEFINE:
            d = c.LutDefinition.unpack(data)
            if d.index >= c.MAX_LUT_ENTRIES:
                raise FirmwareError(f"pattern index {d.index} ≥ {c.MAX_LUT_ENTRIES}",
                                    c.ERR_PATTERN_NUMBER)
            problem = c.exposure_problem(d)
            if problem is not None:
                raise FirmwareError(problem[1], problem[0])
            self.definitions[d.index] = d
        elif command == c.LUT_CONFIG:
            entries, patterns = c.read_lut_config(data)
            missing = [i for i in range(entries) if i not in self.definitions]
            if not entries or missing:
                raise FirmwareError(f"LUT_CONFIG of {entries} entries: patterns {missing[:5]} "
                                    f"are not defined", c.ERR_PATTERN_NUMBER)
            self.entries, self.patterns = entries, patterns
        elif command == c.BMP_LOAD_INIT:
            index, size = struct.unpack("<HI", data)
            if index >= c.MAX_IMAGES:
                raise FirmwareError(f"image index {index} ≥ {c.MAX_IMAGES}",
                                    c.ERR_OUT_OF_RESOURCE)
            self.upload = (index, size, bytearray())
        elif command == c.BMP_LOAD:
            self._bmp_chunk(data)

    def _bmp_chunk(self, data: bytes) -> None:
        if self.upload is None:
            raise FirmwareError("BMP_LOAD before BMP_LOAD_INIT", 5)
        (n,) = struct.unpack_from("<H", data)
        if n != len(data) - 2:
            raise FirmwareError(f"BMP_LOAD chunk says {n} bytes, carries {len(data) - 2}")
        index, size, buf = self.upload
        buf += data[2:]
        if len(buf) > size:
            self.upload = None
            raise FirmwareError(f"image {index}: {len(buf)} bytes exceed the announced {size}")
        if len(buf) == size:
            self.upload = None
            try:
                w, h, _, compression = c900.read_header(bytes(buf))
                if compression not in (c900.UNCOMPRESSED, c900.ENHANCED_RLE):
                    raise FirmwareError(f"image {index}: compression {compression}",
                                        c900.ERR_BAD_COMPRESSION)
                if (w, h) != (self.width, self.height):
                    raise FirmwareError(f"image {index} is {w} x {h}, the DMD "
                                        f"{self.width} x {self.height}")
                self.uploaded[index] = c900.decode_image(bytes(buf))
            except ValueError as exc:
                raise FirmwareError(f"image {index}: {exc}") from None

    def _start_stop(self, action: int) -> None:
        if action != c900.START:
            self.running = False
            return
        if self.mode != c900.MODE_ON_THE_FLY or not self.entries:
            raise FirmwareError("start: no pattern LUT configured", c900.ERR_NOT_ALLOWED)
        defs = [self.definitions[i] for i in range(self.entries)]
        for d in defs:
            if d.image_index not in self.uploaded:
                raise FirmwareError(f"pattern {d.index}: image {d.image_index} not loaded",
                                    c900.ERR_BMP_MISSING)
        first = defs[0]
        self.period_s = (first.exposure_us + first.dark_us) * 1e-6
        self.repeat = self.patterns == 0
        self.running = True

    def images(self) -> list[np.ndarray]:
        return [c900.plane(self.uploaded[d.image_index], d.bit_position, d.bit_depth)
                for d in (self.definitions[i] for i in range(self.entries))]


def flash_images(layout: list[dict[str, Any]], width: int, height: int) -> list[list[np.ndarray]]:
    """The DLPC350's flash as a commissioning layout describes it: per image, 3 8-bit planes."""
    planes: dict[tuple[int, int], np.ndarray] = {}
    for entry in layout:
        if entry["kind"] == "levels":
            pats = [np.full((height, width), int(v), np.uint8) for v in entry["levels"]]
        else:
            patterns = sequence_pattern_set(entry)
            pats = [patterns.image(k, width, height) for k in range(len(patterns))]
            if entry.get("precompensation") is not None:
                lut = np.asarray(entry["precompensation"], np.uint8)
                pats = [lut[p] for p in pats]
        for i, p in enumerate(pats):
            planes[(int(entry["first_image"]) + i // 3, i % 3)] = p
    count = max((img for img, _ in planes), default=-1) + 1
    black = np.zeros((height, width), np.uint8)
    return [[planes.get((img, k), black) for k in range(3)] for img in range(count)]


class DlpEmulatorServer:
    """The TCP server of one emulated controller (``model`` "dlpc350" or "dlpc900")."""

    def __init__(self, model: str, host: str = "127.0.0.1", port: int = 7100,
                 display: Display | None = None, flash: list[dict[str, Any]] | None = None,
                 dmd: tuple[int, int] = (1280, 800)) -> None:
        if model == "dlpc350":
            self.firmware: Firmware = Dlpc350Firmware(flash or [], *dmd)
        elif model == "dlpc900":
            self.firmware = Dlpc900Firmware(*dmd)
        else:
            raise ValueError(f"unknown projector model {model!r}: dlpc350 or dlpc900")
        self.model, self.host, self.port = model, host, port
        self.display = display or NullDisplay()
        self.faults: dict[str, int] = {}
        self.reports = 0
        self.bad_reports = 0
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._player: asyncio.Task | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._unplugged_until = 0.0

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._server = await asyncio.start_server(self._client, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("%s emulator on %s:%d", self.model, self.host, self.port)

    async def close(self) -> None:
        if self._player is not None:
            self._player.cancel()
        if self._server is not None:
            self._server.close()
        for w in list(self._writers):
            w.close()
        if self._server is not None:
            with contextlib.suppress(Exception):
                await self._server.wait_closed()

    def inject(self, fault: str, value: float | None = None) -> None:
        """``drop_reply`` (count), ``validation`` (status bits of the next validation),
        ``disconnect`` (cut every connection now and refuse new ones for ``value`` s, default 0:
        a pulled cable). Callable from any thread."""
        if fault == "disconnect":
            self._unplugged_until = time.monotonic() + float(value or 0.0)

            def cut() -> None:
                for w in list(self._writers):
                    w.close()

            self._loop.call_soon_threadsafe(cut)
        elif fault == "validation":
            if not value:
                raise ValueError("validation fault: give the status bits to report")
            self.firmware.forced_validation = int(value)
        elif fault == "drop_reply":
            self.faults["drop_reply"] = self.faults.get("drop_reply", 0) + int(value or 1)
        else:
            raise ValueError(f"unknown fault {fault!r}: drop_reply, validation or disconnect")

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if time.monotonic() < self._unplugged_until:
            writer.close()
            return
        self._writers.add(writer)
        try:
            while True:
                first = await reader.readexactly(dlp_hid.REPORT_SIZE)
                self.reports += 1
                try:
                    total = dlp_hid.reports_needed(first)
                except dlp_hid.HidFrameError as exc:
                    await self._refuse(writer, first, str(exc))
                    continue
                rest = [await reader.readexactly(dlp_hid.REPORT_SIZE) for _ in range(total - 1)]
                await self._message(writer, dlp_hid.join_reports([first, *rest]))
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            self._writers.discard(writer)
            writer.close()

    async def _refuse(self, writer: asyncio.StreamWriter, report: bytes, why: str) -> None:
        """A report whose header cannot be honoured: error reply (if one is asked for)."""
        self.bad_reports += 1
        log.warning("%s emulator: bad report: %s", self.model, why)
        if isinstance(self.firmware, Dlpc900Firmware):
            self.firmware.error = (c900.ERR_INVALID_PARAMETER, why)
        if report[0] & (dlp_hid.FLAG_REPLY | dlp_hid.FLAG_READ):
            await self._send(writer, dlp_hid.Reply(report[0] | dlp_hid.FLAG_ERROR, report[1]))

    async def _message(self, writer: asyncio.StreamWriter, message: bytes) -> None:
        try:
            req = dlp_hid.decode_request(message)
        except dlp_hid.HidFrameError as exc:
            await self._refuse(writer, message[:dlp_hid.REPORT_SIZE], str(exc))
            return
        flags = req.flags
        was_running = self.firmware.running
        name = dlp_hid.command_name(self.firmware.names, req.command)
        try:
            data = self.firmware.handle(req)
        except FirmwareError as exc:
            self.bad_reports += 1
            log.info("%s emulator: %s refused: %s", self.model, name, exc)
            if req.reply or req.read:
                await self._send(writer, dlp_hid.Reply(flags | dlp_hid.FLAG_ERROR, req.seq))
            return
        except Exception as exc:  # a fault of the emulator itself: an error reply, the link stays
            self.bad_reports += 1
            log.exception("%s emulator: %s failed inside the emulator", self.model, name)
            if isinstance(self.firmware, Dlpc900Firmware):
                self.firmware.error = (c900.ERR_INVALID_COMMAND, f"{name}: internal error: {exc}")
            if req.reply or req.read:
                await self._send(writer, dlp_hid.Reply(flags | dlp_hid.FLAG_ERROR, req.seq))
            return
        if self.firmware.running and not was_running:
            self._play()
        elif was_running and not self.firmware.running and self._player is not None:
            self._player.cancel()
            self.display.show(-1)
        if req.reply or req.read:
            await self._send(writer, dlp_hid.Reply(flags, req.seq, data))

    async def _send(self, writer: asyncio.StreamWriter, reply: dlp_hid.Reply) -> None:
        if self.faults.get("drop_reply", 0) > 0:
            self.faults["drop_reply"] -= 1
            return
        for report in dlp_hid.to_reports(dlp_hid.encode_reply(reply)):
            writer.write(report)
        await writer.drain()

    def _play(self) -> None:
        fw = self.firmware
        self._player = asyncio.get_running_loop().create_task(
            self._run(fw.period_s, fw.repeat))

    async def _run(self, period_s: float, repeat: bool) -> None:
        """Play the firmware's images in LUT order at ``period_s``; they are gathered and the
        display loaded in a thread, since the simulated cell may be busy rendering (no command
        changes the sequence while it runs)."""
        fw = self.firmware
        images: list[np.ndarray] = await asyncio.to_thread(fw.images)
        held = repeat and len(images) == 1  # one pattern held: one exposure's trigger
        try:
            if not images:
                log.info("%s emulator: sequence running on the video port, which has no "
                         "signal here", self.model)
                return
            try:
                await asyncio.to_thread(self.display.load, images)
            except ValueError as exc:  # an image the simulated cell cannot render
                log.error("%s emulator: %s", self.model, exc)
                fw.running = False
                return
            for i in range(1 if held else len(images)):
                self.display.show(i)
                if not held:
                    await asyncio.sleep(period_s)
            if not held:
                self.display.show(-1)
        finally:
            if not held and images:
                fw.running = False
