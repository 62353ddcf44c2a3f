"""Leica emScon TPI packets: the binary protocol of AT4xx/AT9xx laser trackers over TCP (port 700).

A pure codec: bytes in, packets out, no I/O. Layouts follow the public C API header
``ES_C_API_Def.h`` (emScon TPI/SDK 3.6): ``#pragma pack(4)``, little endian (the server is an
x86 Windows or embedded controller), ``long``, ``int``, ``ES_BOOL`` and every ``enum`` 4 bytes,
``double`` 8 bytes. With pack(4) no field of the structs used here needs padding.

Every packet starts with ``PacketHeaderT { long lPacketSize; enum ES_DataType type; }``:
the whole packet's size in bytes, header included, and what follows. A command
(``ES_DT_Command``) continues with ``enum ES_Command command`` (``BasicCommandCT``, 12 bytes)
and its parameters; its reply with the command and ``enum ES_ResultStatus status``
(``BasicCommandRT``, 16 bytes) and its results. Measurements, status changes and errors come as
their own data types. protocols/EMSCON.md lists what is implemented and every reading taken.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any


class DataType(IntEnum):
    """``ES_DataType``."""

    COMMAND = 0
    ERROR = 1
    SINGLE_MEAS_RESULT = 2
    MULTI_MEAS_RESULT = 3
    NIVEL_RESULT = 6
    REFLECTOR_POS_RESULT = 7
    SYSTEM_STATUS_CHANGE = 8
    SINGLE_MEAS_RESULT2 = 9
    MULTI_MEAS_RESULT2 = 10


class Command(IntEnum):
    """The ``ES_Command`` values a scanning cell uses (the header's numbering)."""

    GET_SYSTEM_STATUS = 1
    GET_TRACKER_STATUS = 2
    SET_UNITS = 5
    GET_UNITS = 6
    INITIALIZE = 7
    SET_ENVIRONMENT_PARAMS = 20
    GET_ENVIRONMENT_PARAMS = 21
    SET_REFRACTION_PARAMS = 22
    GET_REFRACTION_PARAMS = 23
    SET_MEASUREMENT_MODE = 24
    GET_MEASUREMENT_MODE = 25
    SET_COORDINATE_SYSTEM_TYPE = 26
    GET_COORDINATE_SYSTEM_TYPE = 27
    SET_STATIONARY_MODE_PARAMS = 28
    GET_STATIONARY_MODE_PARAMS = 29
    SET_CONTINUOUS_TIME_MODE_PARAMS = 30
    GET_CONTINUOUS_TIME_MODE_PARAMS = 31
    SET_CONTINUOUS_DISTANCE_MODE_PARAMS = 32
    GET_CONTINUOUS_DISTANCE_MODE_PARAMS = 33
    SET_REFLECTOR = 40
    GET_REFLECTOR = 41
    GET_REFLECTORS = 42
    START_MEASUREMENT = 49
    STOP_MEASUREMENT = 52
    CHANGE_FACE = 53
    GO_POSITION = 55
    FIND_REFLECTOR = 63
    GET_FACE = 98


class ResultStatus(IntEnum):
    """``ES_ResultStatus`` values this codec names (any other code decodes as a plain int)."""

    ALL_OK = 0
    SERVER_BUSY = 1
    NOT_IMPLEMENTED = 2
    WRONG_PARAMETER = 3
    WRONG_PARAMETER1 = 4
    WRONG_PARAMETER2 = 5
    WRONG_PARAMETER3 = 6
    WRONG_PARAMETER4 = 7
    WRONG_PARAMETER5 = 8
    PARAMETER1_OUT_OF_RANGE_NOK = 12
    PARAMETER2_OUT_OF_RANGE_NOK = 14
    PARAMETER3_OUT_OF_RANGE_NOK = 16
    WRONG_CURRENT_REFLECTOR = 23
    NO_TP_FOUND = 26
    UNKNOWN = 36
    NO_DISTANCE_SET = 37
    TRACKER_NOT_INITIALIZED = 39
    METEO_DATA_OUT_OF_RANGE = 57
    INVALID_INPUT_DATA = 98
    MEASUREMENT_STATUS_NOT_READY = 10004
    SYSTEM_NOT_READY_FOR_MEASUREMENT = 10014
    COMMUNICATION_WITH_SENSOR_FAILED = 10015


class MeasMode(IntEnum):
    """``ES_MeasMode`` (3D modes)."""

    STATIONARY = 0
    CONTINUOUS_TIME = 1
    CONTINUOUS_DISTANCE = 2


class TrackerStatusCode(IntEnum):
    """``ES_TrackerStatus``: the tracker's ready light."""

    NOT_READY = 0
    BUSY = 1
    READY = 2


class SystemStatusChange(IntEnum):
    """``ES_SystemStatusChange`` values the emulator sends and the driver reads."""

    ENVIRONMENT_PARAMS_CHANGED = 2
    REFRACTION_PARAMS_CHANGED = 3
    UNITS_CHANGED = 6
    REFLECTOR_CHANGED = 7
    COORDINATE_SYSTEM_TYPE_CHANGED = 12
    MEASUREMENT_MODE_CHANGED = 17
    MEAS_STATUS_NOT_READY = 25
    MEAS_STATUS_BUSY = 26
    MEAS_STATUS_READY = 27
    MEASUREMENT_COUNT_REACHED = 28
    IS_FACE1 = 30
    IS_FACE2 = 31


class MeasurementStatus(IntEnum):
    """``ES_MeasurementStatus`` of one point of a continuous stream."""

    ALL_OK = 0
    SPEED_WARNING = 1
    SPEED_EXCEEDED = 2
    PRISM_ERROR = 3
    TRIGGER_TIME_VIOLATION = 4


#: ``ES_LengthUnit``, ``ES_AngleUnit``, ``ES_TemperatureUnit``, ``ES_PressureUnit``,
#: ``ES_HumidityUnit`` values scancell sets: mm, degree, °C, mbar (= hPa), % RH
LENGTH_MILLIMETER, ANGLE_DEGREE, TEMPERATURE_CELSIUS, PRESSURE_MBAR, HUMIDITY_RH = 1, 1, 0, 0, 0
#: ``ES_CoordinateSystemType`` right-handed rectangular: dVal1..3 are X, Y, Z
COORDINATES_RHR = 0
#: ``ES_TrackerFace``
FACE_UNKNOWN, FACE1, FACE2 = 0, 1, 2
#: ``ES_TargetType`` of a corner-cube SMR
TARGET_CORNER_CUBE = 1

HEADER = struct.Struct("<iI")  # lPacketSize, type
HEADER_BYTES = HEADER.size
#: the largest packet this codec reads. The header sets no maximum; the largest fixed struct is
#: well under 1 KiB, and a continuous packet of 1000 points (MultiMeasResultT, 36 bytes each)
#: is 36 048 bytes: a length beyond 64 KiB is a broken stream, not a packet.
MAX_PACKET_BYTES = 65536

#: Command parameters after ``BasicCommandCT`` (struct format, field names).
COMMAND_PARAMS: dict[Command, tuple[str, tuple[str, ...]]] = {
    Command.SET_UNITS: ("iiiii", ("length_unit", "angle_unit", "temperature_unit",
                                  "pressure_unit", "humidity_unit")),
    Command.SET_ENVIRONMENT_PARAMS: ("ddd", ("temperature", "pressure", "humidity")),
    Command.SET_REFRACTION_PARAMS: ("dd", ("ifm_refraction_index", "adm_refraction_index")),
    Command.SET_MEASUREMENT_MODE: ("i", ("meas_mode",)),
    Command.SET_COORDINATE_SYSTEM_TYPE: ("i", ("coordinate_system_type",)),
    Command.SET_STATIONARY_MODE_PARAMS: ("ii", ("meas_time_ms", "use_adm")),
    Command.SET_CONTINUOUS_TIME_MODE_PARAMS: ("iiii", ("time_separation_ms", "number_of_points",
                                                      "use_region", "region_type")),
    Command.SET_CONTINUOUS_DISTANCE_MODE_PARAMS: ("diii", ("spatial_distance",
                                                          "number_of_points", "use_region",
                                                          "region_type")),
    Command.SET_REFLECTOR: ("i", ("reflector_id",)),
    Command.GO_POSITION: ("dddi", ("val1", "val2", "val3", "use_adm")),
    Command.FIND_REFLECTOR: ("d", ("approx_distance",)),
}
#: Reply results after ``BasicCommandRT``.
REPLY_RESULTS: dict[Command, tuple[str, tuple[str, ...]]] = {
    Command.GET_UNITS: COMMAND_PARAMS[Command.SET_UNITS],
    Command.GET_ENVIRONMENT_PARAMS: COMMAND_PARAMS[Command.SET_ENVIRONMENT_PARAMS],
    Command.GET_REFRACTION_PARAMS: COMMAND_PARAMS[Command.SET_REFRACTION_PARAMS],
    Command.GET_MEASUREMENT_MODE: COMMAND_PARAMS[Command.SET_MEASUREMENT_MODE],
    Command.GET_COORDINATE_SYSTEM_TYPE: COMMAND_PARAMS[Command.SET_COORDINATE_SYSTEM_TYPE],
    Command.GET_STATIONARY_MODE_PARAMS: COMMAND_PARAMS[Command.SET_STATIONARY_MODE_PARAMS],
    Command.GET_CONTINUOUS_TIME_MODE_PARAMS:
        COMMAND_PARAMS[Command.SET_CONTINUOUS_TIME_MODE_PARAMS],
    Command.GET_CONTINUOUS_DISTANCE_MODE_PARAMS:
        COMMAND_PARAMS[Command.SET_CONTINUOUS_DISTANCE_MODE_PARAMS],
    Command.GET_REFLECTOR: ("i", ("reflector_id",)),
    # one reply per reflector (iTotalReflectors of them); the name is 32 UTF-16 code units
    Command.GET_REFLECTORS: ("iiid64s", ("total_reflectors", "reflector_id", "target_type",
                                         "surface_offset", "reflector_name")),
    Command.GET_SYSTEM_STATUS: ("iiiiiiiiii", ("last_result_status", "tracker_processor_status",
                                               "laser_status", "adm_status", "version_major",
                                               "version_minor", "version_build",
                                               "weather_monitor_status", "flags",
                                               "tracker_serial_number")),
    Command.GET_TRACKER_STATUS: ("i", ("tracker_status",)),
    Command.GET_FACE: ("i", ("face",)),
}

#: ``SingleMeasResultT`` after ``ReturnDataT`` (header + status)
SINGLE_RESULT = ("ii17d", ("meas_mode", "is_try_mode", "val1", "val2", "val3", "std1", "std2",
                           "std3", "std_total", "pointing_error1", "pointing_error2",
                           "pointing_error3", "apriori_std1", "apriori_std2", "apriori_std3",
                           "apriori_std_total", "temperature", "pressure", "humidity"))
#: ``MultiMeasResultT`` after ``ReturnDataT``, then ``lNumberOfResults`` x ``MeasValueT``
MULTI_RESULT = ("iii3d", ("number_of_results", "meas_mode", "is_try_mode", "temperature",
                          "pressure", "humidity"))
MEAS_VALUE = ("iii3d", ("status", "time1", "time2", "val1", "val2", "val3"))
REFLECTOR_POS_RESULT = ("ddd", ("val1", "val2", "val3"))


class PacketError(ValueError):
    """Bytes that are not an emScon packet; ``status`` is what a server answers it with."""

    def __init__(self, message: str, status: int = ResultStatus.INVALID_INPUT_DATA,
                 command: int = 0) -> None:
        super().__init__(message)
        self.status = int(status)
        self.command = int(command)


def status_name(code: int) -> str:
    """``ES_RS_<name>`` of a result status, or its number."""
    try:
        return "ES_RS_" + "".join(w.title() for w in ResultStatus(code).name.split("_"))
    except ValueError:
        return f"status {code}"


@dataclass
class Packet:
    """A decoded packet: its data type, for commands and replies the command and (replies,
    errors, results) the status, and the fields of its struct by name."""

    type: int
    command: int | None = None
    status: int | None = None
    fields: dict[str, Any] = field(default_factory=dict)
    #: ``MultiMeasResultT``: one dict per ``MeasValueT``
    values: list[dict[str, Any]] = field(default_factory=list)


@functools.cache
def _layout(fmt: str) -> struct.Struct:
    return struct.Struct("<" + fmt)


def _pack(kind: int, body: bytes) -> bytes:
    return HEADER.pack(HEADER_BYTES + len(body), int(kind)) + body


def _values(fmt: str, names: tuple[str, ...], values: dict[str, Any], what: str) -> tuple:
    missing = [n for n in names if n not in values]
    extra = sorted(set(values) - set(names))
    if missing or extra:
        raise ValueError(f"{what}: {'missing ' + ', '.join(missing) if missing else ''}"
                         f"{'; ' if missing and extra else ''}"
                         f"{'unknown ' + ', '.join(extra) if extra else ''}")
    out = []
    for code, name in zip(_expand(fmt), names, strict=True):
        v = values[name]
        out.append(encode_name(v) if code.endswith("s") else float(v) if code == "d" else int(v))
    return tuple(out)


@functools.cache
def _expand(fmt: str) -> tuple[str, ...]:
    """``"ii17d"`` -> one struct code per field (``"64s"`` stays whole)."""
    out, count = [], ""
    for ch in fmt:
        if ch.isdigit():
            count += ch
        elif ch == "s":
            out.append(count + "s")
            count = ""
        else:
            out += [ch] * int(count or 1)
            count = ""
    return tuple(out)


def encode_name(name: Any) -> bytes:
    """A reflector name as ``unsigned short cReflectorName[32]``: UTF-16LE, NUL-padded."""
    if isinstance(name, bytes):
        return name
    raw = str(name).encode("utf-16-le")[:62]
    return raw + b"\0" * (64 - len(raw))


def decode_name(raw: bytes) -> str:
    text = raw.decode("utf-16-le", errors="replace")
    return text.split("\0", 1)[0]


def encode_command(command: Command | int, **params: Any) -> bytes:
    """A command packet (``<Name>CT``): ``BasicCommandCT`` and the command's parameters."""
    fmt, names = COMMAND_PARAMS.get(Command(command), ("", ()))
    body = struct.pack("<I", int(command))
    if names:
        body += _layout(fmt).pack(*_values(fmt, names, params, Command(command).name))
    elif params:
        raise ValueError(f"{Command(command).name} takes no parameters, got {sorted(params)}")
    return _pack(DataType.COMMAND, body)


def encode_reply(command: Command | int, status: int = ResultStatus.ALL_OK,
                 **results: Any) -> bytes:
    """A reply packet (``<Name>RT``): ``BasicCommandRT`` and the command's results, always the
    whole struct (a failed reply's results are zeros unless given: EMSCON.md)."""
    body = struct.pack("<II", int(command), int(status))
    fmt, names = REPLY_RESULTS.get(Command(command), ("", ()))
    if names:
        if int(status) != ResultStatus.ALL_OK and not results:
            results = {n: b"" if c.endswith("s") else 0 for n, c in zip(names, _expand(fmt),
                                                                       strict=True)}
        body += _layout(fmt).pack(*_values(fmt, names, results, Command(command).name))
    return _pack(DataType.COMMAND, body)


def encode_error(command: int, status: int) -> bytes:
    """``ErrorResponseT``: the command it answers (0 when none could be read) and why."""
    return _pack(DataType.ERROR, struct.pack("<II", int(command), int(status)))


def encode_single_result(status: int = ResultStatus.ALL_OK, **values: Any) -> bytes:
    """``SingleMeasResultT``."""
    fmt, names = SINGLE_RESULT
    return _pack(DataType.SINGLE_MEAS_RESULT, struct.pack("<I", int(status)) + _layout(fmt).pack(
        *_values(fmt, names, values, "SingleMeasResultT")))


def encode_multi_result(points: list[dict[str, Any]], status: int = ResultStatus.ALL_OK,
                        **values: Any) -> bytes:
    """``MultiMeasResultT`` with ``len(points)`` ``MeasValueT`` records."""
    fmt, names = MULTI_RESULT
    body = struct.pack("<I", int(status)) + _layout(fmt).pack(
        *_values(fmt, names, {**values, "number_of_results": len(points)}, "MultiMeasResultT"))
    vfmt, vnames = MEAS_VALUE
    for p in points:
        body += _layout(vfmt).pack(*_values(vfmt, vnames, p, "MeasValueT"))
    return _pack(DataType.MULTI_MEAS_RESULT, body)


def encode_status_change(change: SystemStatusChange | int) -> bytes:
    """``SystemStatusChangeT``."""
    return _pack(DataType.SYSTEM_STATUS_CHANGE, struct.pack("<I", int(change)))


def encode_reflector_position(x: float, y: float, z: float,
                              status: int = ResultStatus.ALL_OK) -> bytes:
    """``ReflectorPosResultT``."""
    return _pack(DataType.REFLECTOR_POS_RESULT, struct.pack("<I3d", int(status), x, y, z))


def packet_size(header: bytes) -> int:
    """The whole packet's size from its first 8 bytes; PacketError if no packet is that long
    (shorter than a header, or beyond :data:`MAX_PACKET_BYTES`)."""
    size, _ = HEADER.unpack_from(header)
    if size < HEADER_BYTES or size > MAX_PACKET_BYTES:
        raise PacketError(f"packet length {size} outside {HEADER_BYTES}..{MAX_PACKET_BYTES} "
                          f"bytes", ResultStatus.INVALID_INPUT_DATA)
    return size


def _fields(fmt: str, names: tuple[str, ...], data: bytes, offset: int, what: str
            ) -> dict[str, Any]:
    layout = _layout(fmt)
    if len(data) < offset + layout.size:
        raise PacketError(f"{what}: {len(data)} bytes, needs {offset + layout.size}")
    out = dict(zip(names, layout.unpack_from(data, offset), strict=True))
    if "reflector_name" in out:
        out["reflector_name"] = decode_name(out["reflector_name"])
    return out


def _exact(data: bytes, size: int, what: str, command: int = 0) -> None:
    if len(data) != size:
        raise PacketError(f"{what}: {len(data)} bytes where the header defines {size}",
                          ResultStatus.INVALID_INPUT_DATA, command)


def decode_command(data: bytes) -> Packet:
    """A client's command packet (what a server reads). PacketError names what is wrong and
    carries the status a server answers with: an unknown data type or command is
    ``ES_RS_NotImplemented``, a wrong size ``ES_RS_InvalidInputData``."""
    size = _checked_size(data)
    _, kind = HEADER.unpack_from(data)
    if kind != DataType.COMMAND:
        raise PacketError(f"data type {kind} is not a command (ES_DT_Command = 0)",
                          ResultStatus.NOT_IMPLEMENTED)
    if size < HEADER_BYTES + 4:
        raise PacketError(f"a command packet of {size} bytes has no command field")
    (command,) = struct.unpack_from("<I", data, HEADER_BYTES)
    try:
        cmd = Command(command)
    except ValueError:
        raise PacketError(f"command {command} is not implemented", ResultStatus.NOT_IMPLEMENTED,
                          command) from None
    fmt, names = COMMAND_PARAMS.get(cmd, ("", ()))
    _exact(data, HEADER_BYTES + 4 + (_layout(fmt).size if names else 0), f"{cmd.name}CT",
           command)
    fields = _fields(fmt, names, data, HEADER_BYTES + 4, cmd.name) if names else {}
    return Packet(DataType.COMMAND, int(cmd), None, fields)


def decode_reply(data: bytes) -> Packet:
    """A server's packet (what a client reads): a command's reply, an error, a measurement,
    a status change or a reflector position."""
    size = _checked_size(data)
    _, kind = HEADER.unpack_from(data)
    off = HEADER_BYTES
    if kind in (DataType.COMMAND, DataType.ERROR):
        if size < off + 8:
            raise PacketError(f"a reply of {size} bytes has no command and status")
        command, status = struct.unpack_from("<II", data, off)
        if kind == DataType.ERROR:
            _exact(data, off + 8, "ErrorResponseT", command)
            return Packet(DataType.ERROR, command, status)
        fmt, names = REPLY_RESULTS.get(Command(command), ("", ())) \
            if command in Command._value2member_map_ else ("", ())
        full = off + 8 + (_layout(fmt).size if names else 0)
        if names and (status == ResultStatus.ALL_OK or size == full):
            _exact(data, full, f"reply to command {command}", command)
            return Packet(DataType.COMMAND, command, status, _fields(fmt, names, data, off + 8,
                                                                     "reply"))
        # a failed reply may also come as the bare BasicCommandRT
        _exact(data, off + 8, f"reply to command {command}", command)
        return Packet(DataType.COMMAND, command, status)
    if kind == DataType.SINGLE_MEAS_RESULT:
        fmt, names = SINGLE_RESULT
        _exact(data, off + 4 + _layout(fmt).size, "SingleMeasResultT")
        (status,) = struct.unpack_from("<I", data, off)
        return Packet(kind, None, status, _fields(fmt, names, data, off + 4, "SingleMeasResultT"))
    if kind == DataType.MULTI_MEAS_RESULT:
        fmt, names = MULTI_RESULT
        (status,) = struct.unpack_from("<I", data, off)
        head = _fields(fmt, names, data, off + 4, "MultiMeasResultT")
        vfmt, vnames = MEAS_VALUE
        start, step = off + 4 + _layout(fmt).size, _layout(vfmt).size
        n = head["number_of_results"]
        if n < 0:
            raise PacketError(f"MultiMeasResultT: {n} results")
        _exact(data, start + n * step, f"MultiMeasResultT of {n} points")
        values = [_fields(vfmt, vnames, data, start + i * step, "MeasValueT") for i in range(n)]
        return Packet(kind, None, status, head, values)
    if kind == DataType.SYSTEM_STATUS_CHANGE:
        _exact(data, off + 4, "SystemStatusChangeT")
        (change,) = struct.unpack_from("<I", data, off)
        return Packet(kind, None, None, {"change": change})
    if kind == DataType.REFLECTOR_POS_RESULT:
        fmt, names = REFLECTOR_POS_RESULT
        _exact(data, off + 4 + _layout(fmt).size, "ReflectorPosResultT")
        (status,) = struct.unpack_from("<I", data, off)
        return Packet(kind, None, status, _fields(fmt, names, data, off + 4,
                                                  "ReflectorPosResultT"))
    raise PacketError(f"data type {kind} is not one this client reads", ResultStatus.NOT_IMPLEMENTED)


def _checked_size(data: bytes) -> int:
    if len(data) < HEADER_BYTES:
        raise PacketError(f"{len(data)} bytes: shorter than the 8-byte packet header")
    size = packet_size(data)
    if size != len(data):
        raise PacketError(f"the header says {size} bytes, the packet has {len(data)}")
    return size


class PacketSplitter:
    """Cuts a TCP byte stream into packets by their length field. A length outside
    :data:`MAX_PACKET_BYTES` leaves the stream without a frame to resynchronise on: ``feed``
    raises PacketError and the splitter stays broken (the link must be closed)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.broken: PacketError | None = None

    def feed(self, data: bytes) -> list[bytes]:
        if self.broken is not None:
            raise self.broken
        self._buf += data
        out = []
        while len(self._buf) >= HEADER_BYTES:
            try:
                size = packet_size(bytes(self._buf[:HEADER_BYTES]))
            except PacketError as exc:
                self.broken = exc
                raise
            if len(self._buf) < size:
                break
            out.append(bytes(self._buf[:size]))
            del self._buf[:size]
        return out

    @property
    def pending(self) -> int:
        """Bytes of an incomplete packet held."""
        return len(self._buf)
