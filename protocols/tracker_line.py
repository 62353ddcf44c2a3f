"""Codec of the scancell tracker line protocol (STLP, see TRACKER_PROTOCOL.md). Pure: no I/O."""

from __future__ import annotations

import re
from dataclasses import dataclass

MAX_LINE = 1024
EVENT_TAG = "E0000"

ERRORS = {
    1001: "BeamBroken", 1002: "NoReflector", 2001: "UnknownCommand", 2002: "BadArguments",
    2003: "BadLine", 2004: "Busy", 3001: "HardwareFault",
}

Value = float | int | str


class LineError(ValueError):
    """A line that does not follow the protocol grammar."""


_CALL = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)\((.*)\)$")
_TAG = re.compile(r"^\d{5}$")
_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")


def _split_args(text: str) -> list[Value]:
    args: list[Value] = []
    i, n = 0, len(text)
    while i < n:
        while i < n and text[i] == " ":
            i += 1
        if i >= n:
            raise LineError("empty argument")
        if text[i] == '"':
            j, out = i + 1, []
            while j < n and text[j] != '"':
                if text[j] == "\\" and j + 1 < n:
                    j += 1
                out.append(text[j])
                j += 1
            if j >= n:
                raise LineError("unterminated string")
            args.append("".join(out))
            i = j + 1
        else:
            j = text.find(",", i)
            j = n if j < 0 else j
            tok = text[i:j].strip()
            if not _NUMBER.match(tok):
                raise LineError(f"not a number or quoted string: {tok[:40]!r}")
            args.append(float(tok) if any(c in tok for c in ".eE") else int(tok))
            i = j
        while i < n and text[i] == " ":
            i += 1
        if i < n:
            if text[i] != ",":
                raise LineError(f"expected ',' at {text[i:i + 10]!r}")
            i += 1
            if i >= n:
                raise LineError("trailing ','")
    return args


def parse_call(text: str) -> tuple[str, list[Value]]:
    """``Name(a, b, "c")`` -> ("Name", [a, b, "c"])."""
    m = _CALL.match(text.strip())
    if not m:
        raise LineError(f"not a call Name(args): {text[:60]!r}")
    return m.group(1), _split_args(m.group(2)) if m.group(2).strip() else []


def _printable(text: str) -> str:
    """Strings on the wire are printable ASCII: anything else becomes '?'."""
    return "".join(c if " " <= c <= "~" else "?" for c in text)


def _fmt(v: Value) -> str:
    if isinstance(v, str):
        return '"' + _printable(v).replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return str(int(v))
    if isinstance(v, int):
        return str(v)
    return repr(float(v))


def format_call(name: str, args: list[Value] | tuple[Value, ...] = ()) -> str:
    return f"{name}({', '.join(_fmt(a) for a in args)})"


def format_command(tag: int, name: str, args: list[Value] | tuple[Value, ...] = ()) -> bytes:
    if not 1 <= tag <= 99999:
        raise ValueError(f"tag {tag} outside 1..99999")
    return f"{tag:05d} {format_call(name, args)}\r\n".encode("ascii")


def parse_command(line: str) -> tuple[str, str, list[Value]]:
    """Server side: (tag, name, args)."""
    line = line.rstrip("\r\n")
    if len(line) > MAX_LINE:
        raise LineError(f"line longer than {MAX_LINE} bytes")
    tag, _, call = line.partition(" ")
    if not _TAG.match(tag):
        raise LineError(f"bad tag {tag[:10]!r}: 5 digits expected")
    name, args = parse_call(call)
    return tag, name, args


@dataclass(frozen=True)
class Response:
    tag: str
    kind: str  # "ack" | "data" | "done" | "error" | "event"
    name: str = ""
    args: tuple[Value, ...] = ()

    @property
    def error_code(self) -> int:
        return int(self.args[0]) if self.kind == "error" else 0

    @property
    def error_text(self) -> str:
        return str(self.args[1]) if self.kind == "error" and len(self.args) > 1 else ""


def format_response(tag: str, kind: str, name: str = "", args: tuple[Value, ...] = ()) -> bytes:
    body = {"ack": "&", "done": "%"}.get(kind)
    if body is None:
        mark = "!" if kind == "error" else "#"
        body = f"{mark} {format_call('Error' if kind == 'error' else name, list(args))}"
    return f"{tag} {body}\r\n".encode("ascii", "replace")  # the grammar is ASCII


def error_response(tag: str, code: int, text: str) -> bytes:
    message = f"{ERRORS.get(code, 'Error')}: {text}"[: MAX_LINE // 2]
    return format_response(tag, "error", "Error", (code, message))


def parse_response(line: str) -> Response:
    """Client side: one line from the server."""
    line = line.rstrip("\r\n")
    if len(line) > MAX_LINE:
        raise LineError(f"line longer than {MAX_LINE} bytes")
    tag, _, rest = line.partition(" ")
    if not (_TAG.match(tag) or tag == EVENT_TAG):
        raise LineError(f"bad tag {tag[:10]!r}")
    if tag == EVENT_TAG:
        if not rest.startswith("# "):
            raise LineError(f"event without '# ': {line[:60]!r}")
        name, args = parse_call(rest[2:])
        return Response(tag, "event", name, tuple(args))
    if rest == "&":
        return Response(tag, "ack")
    if rest == "%":
        return Response(tag, "done")
    if rest.startswith("# "):
        name, args = parse_call(rest[2:])
        return Response(tag, "data", name, tuple(args))
    if rest.startswith("! "):
        name, args = parse_call(rest[2:])
        if name != "Error" or len(args) != 2 or not isinstance(args[0], int):
            raise LineError(f"malformed error line: {line[:60]!r}")
        return Response(tag, "error", name, tuple(args))
    raise LineError(f"unknown response kind: {line[:60]!r}")


class LineSplitter:
    """Bytes in, complete lines out; an over-long line raises LineError and is dropped."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[str]:
        self._buf += data
        lines = []
        while (i := self._buf.find(b"\n")) >= 0:
            raw = bytes(self._buf[:i]).rstrip(b"\r")
            del self._buf[: i + 1]
            if len(raw) > MAX_LINE:
                raise LineError(f"line longer than {MAX_LINE} bytes")
            try:
                lines.append(raw.decode("ascii"))
            except UnicodeDecodeError:
                raise LineError(f"non-ASCII bytes in line {raw[:40]!r}") from None
        if len(self._buf) > MAX_LINE:
            self._buf.clear()
            raise LineError(f"line longer than {MAX_LINE} bytes without a terminator")
        return lines
