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
    """A line that does not follow the protocol grammar; ``tag`` is the line's tag when its
    first five characters could be read as one (the reply to it then carries that tag)."""

    def __init__(self, message: str, tag: str | None = None) -> None:
        super().__init__(message)
        self.tag = tag


#: The tag of an error reply to a line whose own tag cannot be read.
NO_TAG = "00000"


def readable_tag(text: str | bytes) -> str | None:
    """The tag a (possibly broken) command line starts with: five digits and a space."""
    head = text[:6].decode("ascii", "replace") if isinstance(text, bytes) else text[:6]
    return head[:5] if len(head) == 6 and _TAG.match(head[:5]) and head[5] == " " else None


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
    tag = readable_tag(line)
    if len(line) > MAX_LINE:
        raise LineError(f"line longer than {MAX_LINE} bytes", tag)
    head, _, call = line.partition(" ")
    if tag is None:
        raise LineError(f"bad tag {head[:10]!r}: 5 digits and a space expected")
    try:
        name, args = parse_call(call)
    except LineError as exc:
        raise LineError(str(exc), tag) from None
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
    """Bytes in, lines out, in order: each complete line as ``str``, each line that cannot be
    passed on as one ``LineError`` (carrying its tag when readable).

    A line longer than ``MAX_LINE`` gives one error however long it is: its bytes are dropped up
    to and including the next line end, so no part of it is ever taken for a command.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._discarding = False  # inside an over-long line, until its line end

    def feed(self, data: bytes) -> list[str | LineError]:
        self._buf += data
        out: list[str | LineError] = []
        while True:
            i = self._buf.find(b"\n")
            if self._discarding:
                if i < 0:
                    self._buf.clear()
                    return out
                del self._buf[: i + 1]
                self._discarding = False
                continue
            if i < 0:
                if len(self._buf) > MAX_LINE:  # over-long: say so once, drop the rest of it
                    out.append(LineError(f"line longer than {MAX_LINE} bytes",
                                         readable_tag(bytes(self._buf[:6]))))
                    self._buf.clear()
                    self._discarding = True
                return out
            raw = bytes(self._buf[:i]).rstrip(b"\r")
            del self._buf[: i + 1]
            if len(raw) > MAX_LINE:
                out.append(LineError(f"line longer than {MAX_LINE} bytes", readable_tag(raw)))
                continue
            try:
                out.append(raw.decode("ascii"))
            except UnicodeDecodeError:
                out.append(LineError(f"non-ASCII bytes in line {raw[:40]!r}", readable_tag(raw)))


#: the air a tracker's refraction correction accepts: (name, unit, low, high)
ENVIRONMENT_RANGES = (("air temperature", "°C", -10.0, 50.0),
                      ("air pressure", "hPa", 500.0, 1100.0),
                      ("relative humidity", "%", 0.0, 100.0))


def environment_problem(temperature_c: float, pressure_hpa: float, humidity_pct: float
                        ) -> str | None:
    """The first weather value out of its range, named with the range, or None."""
    for (name, unit, lo, hi), v in zip(ENVIRONMENT_RANGES,
                                       (temperature_c, pressure_hpa, humidity_pct), strict=True):
        if not lo <= v <= hi:  # also refuses NaN
            return f"{name} {v:g} {unit} outside [{lo:g}, {hi:g}] {unit}"
    return None
