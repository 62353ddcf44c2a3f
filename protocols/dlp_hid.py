"""USB HID framing shared by TI's DLPC350 and DLPC900 controllers. Pure: no I/O.

A message (DLPU010 §1.3, DLPU018 §1.2) is a 4-byte header and a payload:

- flags: bit 7 read (1) / write (0), bit 6 the host wants a reply, bit 5 error (set by the
  device in a reply: command not found or failed), bits 2:0 destination (0 = the controller);
- sequence: echoed by the device in its reply;
- length (LSB first): the number of payload bytes;
- payload of a request: the 16-bit command (LSB first, e.g. 0x1A1B -> ``1B 1A``) and its data;
  payload of a reply: the data only.

A message travels in 64-byte HID reports: the first report carries the header and up to 60
payload bytes, each following report 64 more; the last report is zero-padded. hidapi prepends a
report-ID byte (always 0) to each report it writes; that byte is not part of the report and is
not counted here. Over TCP (``socket://``, the emulator) the 64-byte reports are sent as they
are, back to back (see protocols/DLP_HID_PROTOCOL.md).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

REPORT_SIZE = 64
HEADER_SIZE = 4
#: The controllers' command buffer (DLPU018 §1.2.1: 512 bytes shared by write and read).
MAX_PAYLOAD = 512

FLAG_READ = 0x80
FLAG_REPLY = 0x40
FLAG_ERROR = 0x20
DEST_MASK = 0x07


# Commands both controllers define alike (DLPU010, DLPU018).
GET_VERSION = 0x0205        # read: application, API, software-config, sequence-config (4 x u32)
PAT_START_STOP = 0x1A24     # 1 byte: 0 stop, 1 pause, 2 start
START, PAUSE, STOP = 2, 1, 0
VERSION_NAMES = ("application", "api", "software_config", "sequence_config")


class HidFrameError(ValueError):
    """Bytes that are not a well-formed DLPC HID message."""


@dataclass(frozen=True)
class Request:
    """A host -> controller message: ``command`` with its ``data`` bytes."""

    command: int
    data: bytes = b""
    read: bool = False
    reply: bool = True
    seq: int = 0
    dest: int = 0

    @property
    def flags(self) -> int:
        return (FLAG_READ if self.read else 0) | (FLAG_REPLY if self.reply else 0) | (
            self.dest & DEST_MASK)


@dataclass(frozen=True)
class Reply:
    """A controller -> host message; ``error`` is the flags' bit 5 (DLPC350: "nack")."""

    flags: int
    seq: int
    data: bytes = b""

    @property
    def error(self) -> bool:
        return bool(self.flags & FLAG_ERROR)


def _header(flags: int, seq: int, length: int) -> bytes:
    if not 0 <= length <= MAX_PAYLOAD:
        raise HidFrameError(f"payload of {length} bytes: the controller takes at most "
                            f"{MAX_PAYLOAD}")
    return struct.pack("<BBH", flags & 0xFF, seq & 0xFF, length)


def encode_request(req: Request) -> bytes:
    """The message bytes of ``req`` (header, command, data; not yet split into reports)."""
    if not 0 <= req.command <= 0xFFFF:
        raise HidFrameError(f"command 0x{req.command:X} is not 16 bits")
    payload = struct.pack("<H", req.command) + bytes(req.data)
    return _header(req.flags, req.seq, len(payload)) + payload


def encode_reply(reply: Reply) -> bytes:
    return _header(reply.flags, reply.seq, len(reply.data)) + bytes(reply.data)


def to_reports(message: bytes) -> list[bytes]:
    """Split a message into 64-byte reports, the last zero-padded."""
    reports = [message[i:i + REPORT_SIZE] for i in range(0, max(len(message), 1), REPORT_SIZE)]
    reports[-1] = reports[-1].ljust(REPORT_SIZE, b"\0")
    return reports


def message_length(first_report: bytes) -> int:
    """Total bytes (header + payload) of the message that ``first_report`` starts."""
    if len(first_report) < HEADER_SIZE:
        raise HidFrameError(f"report of {len(first_report)} bytes is shorter than the "
                            f"{HEADER_SIZE}-byte header")
    (length,) = struct.unpack_from("<H", first_report, 2)
    if length > MAX_PAYLOAD:
        raise HidFrameError(f"length field {length} exceeds the controller's {MAX_PAYLOAD}-byte "
                            f"command buffer")
    return HEADER_SIZE + length


def reports_needed(first_report: bytes) -> int:
    """How many 64-byte reports the message starting with ``first_report`` spans."""
    return -(-message_length(first_report) // REPORT_SIZE)


def join_reports(reports: list[bytes]) -> bytes:
    """The message bytes carried by ``reports`` (padding removed)."""
    data = b"".join(reports)
    n = message_length(data)
    if len(data) < n:
        raise HidFrameError(f"message truncated: {len(data)} of {n} bytes")
    return data[:n]


def decode_request(message: bytes) -> Request:
    n = message_length(message)
    if len(message) < n:
        raise HidFrameError(f"message truncated: {len(message)} of {n} bytes")
    if n < HEADER_SIZE + 2:
        raise HidFrameError("request without a command (length field < 2)")
    flags, seq = message[0], message[1]
    (command,) = struct.unpack_from("<H", message, HEADER_SIZE)
    return Request(command, bytes(message[HEADER_SIZE + 2:n]), bool(flags & FLAG_READ),
                   bool(flags & FLAG_REPLY), seq, flags & DEST_MASK)


def decode_reply(message: bytes) -> Reply:
    n = message_length(message)
    if len(message) < n:
        raise HidFrameError(f"reply truncated: {len(message)} of {n} bytes")
    return Reply(message[0], message[1], bytes(message[HEADER_SIZE:n]))


def u24(value: int) -> bytes:
    """A 24-bit unsigned integer, LSB first."""
    if not 0 <= value < 1 << 24:
        raise ValueError(f"{value} does not fit 24 bits")
    return struct.pack("<I", value)[:3]


def read_u24(data: bytes, offset: int = 0) -> int:
    return int.from_bytes(data[offset:offset + 3], "little")


def command_name(names: dict[int, str], command: int) -> str:
    return names.get(command, f"0x{command:04X}")


@dataclass(frozen=True)
class Version:
    """A version word: bits 31:24 major, 23:16 minor, 15:0 patch."""

    major: int
    minor: int
    patch: int

    @classmethod
    def from_word(cls, word: int) -> Version:
        return cls(word >> 24, (word >> 16) & 0xFF, word & 0xFFFF)

    def word(self) -> int:
        return self.major << 24 | self.minor << 16 | self.patch

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.patch}"


def read_versions(data: bytes) -> dict[str, Version]:
    """GET_VERSION reply: application, API, software-config and sequence-config versions."""
    words = struct.unpack_from("<4I", data)
    return {name: Version.from_word(w) for name, w in zip(VERSION_NAMES, words, strict=True)}


def pack_versions(versions: dict[str, Version]) -> bytes:
    """The GET_VERSION reply data for ``versions`` (keyed as :data:`VERSION_NAMES`)."""
    return struct.pack("<4I", *(versions[name].word() for name in VERSION_NAMES))
