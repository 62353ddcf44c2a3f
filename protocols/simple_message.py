"""ROS-Industrial simple_message codec (REP-I0004 identifiers, message layouts of the
industrial_core simple_message package). Pure: bytes in, messages out; no I/O.

A packet is ``length`` (int32: bytes of header + body) + header (msg_type, comm_type,
reply_code; int32 each) + body. ``shared_real`` is float32. Byte order is a per-device setting:
FANUC's KAREL server sends big-endian, MotoROS little-endian.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

N_JOINTS = 10
#: Longest body of the standard set (JOINT_TRAJ_PT_FULL request) plus header, with margin.
MAX_LENGTH = 4096


class MsgType(enum.IntEnum):
    PING = 1
    GET_VERSION = 2
    JOINT_POSITION = 10
    JOINT_TRAJ_PT = 11
    JOINT_TRAJ = 12
    STATUS = 13
    JOINT_TRAJ_PT_FULL = 14
    JOINT_FEEDBACK = 15


class CommType(enum.IntEnum):
    INVALID = 0
    TOPIC = 1
    SERVICE_REQUEST = 2
    SERVICE_REPLY = 3


class ReplyCode(enum.IntEnum):
    INVALID = 0
    SUCCESS = 1
    FAILURE = 2


class SpecialSeq(enum.IntEnum):
    START_TRAJECTORY_DOWNLOAD = -1
    START_TRAJECTORY_STREAMING = -2
    END_TRAJECTORY = -3
    STOP_TRAJECTORY = -4


class TriState(enum.IntEnum):
    UNKNOWN = -1
    OFF = 0
    ON = 1


class ValidFields(enum.IntFlag):
    TIME = 1
    POSITION = 2
    VELOCITY = 4
    ACCELERATION = 8


class ProtocolError(ValueError):
    """Bytes that are not a valid simple_message packet (the stream cannot be trusted after)."""


def reals_within(values: Sequence[float], limits: Sequence[Sequence[float]]
                 ) -> tuple[float, ...]:
    """``values`` as ``shared_real`` (float32) carries them, each kept inside its ``(lo, hi)``
    of ``limits``: where rounding to float32 would cross the limit, the float32 next to it on
    the inside. A joint commanded onto its limit (-125 deg is -2.18166156 rad) would otherwise
    reach the controller up to half a float32 step (1.2e-7 rad at 2 rad) outside it, and be
    refused. Values already outside stay as they round."""
    out = []
    for x, (lo, hi) in zip(values, limits, strict=True):
        r = float(np.float32(x))
        if lo <= x and r < lo:
            r = float(np.nextafter(np.float32(r), np.float32(np.inf)))
        elif x <= hi and r > hi:
            r = float(np.nextafter(np.float32(r), np.float32(-np.inf)))
        out.append(r)
    return tuple(out)


def _joints(values) -> tuple[float, ...]:
    v = tuple(float(x) for x in values)
    if len(v) > N_JOINTS:
        raise ValueError(f"at most {N_JOINTS} joints, got {len(v)}")
    return v + (0.0,) * (N_JOINTS - len(v))


@dataclass(frozen=True)
class Header:
    msg_type: int
    comm_type: int = CommType.TOPIC
    reply_code: int = ReplyCode.INVALID


@dataclass(frozen=True)
class Ping:
    data: tuple[int, ...] = (0,) * N_JOINTS


@dataclass(frozen=True)
class JointPosition:
    sequence: int = 0
    joints: tuple[float, ...] = field(default=(0.0,) * N_JOINTS)

    def __post_init__(self) -> None:
        object.__setattr__(self, "joints", _joints(self.joints))


@dataclass(frozen=True)
class JointTrajPt:
    sequence: int
    joints: tuple[float, ...]
    velocity: float = 0.0  # fraction (0, 1] of max joint speed
    duration: float = 0.0  # s

    def __post_init__(self) -> None:
        object.__setattr__(self, "joints", _joints(self.joints))


@dataclass(frozen=True)
class Status:
    drives_powered: int = TriState.UNKNOWN
    e_stopped: int = TriState.UNKNOWN
    error_code: int = 0
    in_error: int = TriState.UNKNOWN
    in_motion: int = TriState.UNKNOWN
    mode: int = -1  # -1 unknown, 1 manual, 2 auto
    motion_possible: int = TriState.UNKNOWN


class _PaddedJointArrays:
    """Pads positions, velocities and accelerations to the protocol's 10 joints."""

    def __post_init__(self) -> None:
        for name in ("positions", "velocities", "accelerations"):
            object.__setattr__(self, name, _joints(getattr(self, name)))


@dataclass(frozen=True)
class JointTrajPtFull(_PaddedJointArrays):
    robot_id: int
    sequence: int
    valid_fields: int
    time: float
    positions: tuple[float, ...]
    velocities: tuple[float, ...] = (0.0,) * N_JOINTS
    accelerations: tuple[float, ...] = (0.0,) * N_JOINTS


@dataclass(frozen=True)
class JointFeedback(_PaddedJointArrays):
    robot_id: int
    valid_fields: int
    time: float
    positions: tuple[float, ...]
    velocities: tuple[float, ...] = (0.0,) * N_JOINTS
    accelerations: tuple[float, ...] = (0.0,) * N_JOINTS


@dataclass(frozen=True)
class DummyReply:
    """The fixed-size reply body: ``dummy_data: shared_real[10]`` (or empty, the short form)."""

    data: tuple[float, ...] | None = (0.0,) * N_JOINTS


Body = Ping | JointPosition | JointTrajPt | Status | JointTrajPtFull | JointFeedback | DummyReply

_I, _F = "i", "f"
_LAYOUTS: dict[type, str] = {
    Ping: _I * 10,
    JointPosition: _I + _F * 10,
    JointTrajPt: _I + _F * 12,
    Status: _I * 7,
    JointTrajPtFull: _I * 3 + _F + _F * 30,
    JointFeedback: _I * 2 + _F + _F * 30,
}


def _fmt(layout: str, byteorder: str) -> struct.Struct:
    return struct.Struct((">" if byteorder == "big" else "<") + layout)


def _flatten(body: Body) -> tuple:
    if isinstance(body, Ping):
        return tuple(body.data)
    if isinstance(body, JointPosition):
        return (body.sequence, *body.joints)
    if isinstance(body, JointTrajPt):
        return (body.sequence, *body.joints, body.velocity, body.duration)
    if isinstance(body, Status):
        return (body.drives_powered, body.e_stopped, body.error_code, body.in_error,
                body.in_motion, body.mode, body.motion_possible)
    if isinstance(body, JointTrajPtFull):
        return (body.robot_id, body.sequence, body.valid_fields, body.time, *body.positions,
                *body.velocities, *body.accelerations)
    if isinstance(body, JointFeedback):
        return (body.robot_id, body.valid_fields, body.time, *body.positions, *body.velocities,
                *body.accelerations)
    raise TypeError(f"not a simple_message body: {body!r}")


def encode(header: Header, body: Body | None, byteorder: str = "big") -> bytes:
    """One complete packet (length prefix + header + body)."""
    if byteorder not in ("big", "little"):
        raise ValueError(f"byteorder must be 'big' or 'little', got {byteorder!r}")
    if body is None or (isinstance(body, DummyReply) and body.data is None):
        payload = b""
    elif isinstance(body, DummyReply):
        payload = _fmt(_F * 10, byteorder).pack(*_joints(body.data))
    else:
        payload = _fmt(_LAYOUTS[type(body)], byteorder).pack(*_flatten(body))
    head = _fmt(_I * 3, byteorder).pack(int(header.msg_type), int(header.comm_type),
                                         int(header.reply_code))
    return _fmt(_I, byteorder).pack(len(head) + len(payload)) + head + payload


def _body_class(header: Header) -> type | None:
    t, c = header.msg_type, header.comm_type
    if c == CommType.SERVICE_REPLY and t in (MsgType.JOINT_TRAJ_PT, MsgType.JOINT_TRAJ_PT_FULL):
        return DummyReply
    return {MsgType.PING: Ping, MsgType.JOINT_POSITION: JointPosition,
            MsgType.JOINT_TRAJ_PT: JointTrajPt, MsgType.STATUS: Status,
            MsgType.JOINT_TRAJ_PT_FULL: JointTrajPtFull,
            MsgType.JOINT_FEEDBACK: JointFeedback}.get(t)


def decode_packet(packet: bytes, byteorder: str = "big") -> tuple[Header, Body | bytes]:
    """Decode header + body (without the length prefix). Unknown types give the raw body bytes."""
    if len(packet) < 12:
        raise ProtocolError(f"packet of {len(packet)} bytes is shorter than a header (12)")
    t, c, r = _fmt(_I * 3, byteorder).unpack_from(packet)
    if c not in (1, 2, 3):
        raise ProtocolError(f"comm_type {c} is not TOPIC, SERVICE_REQUEST or SERVICE_REPLY")
    if r not in (0, 1, 2):
        raise ProtocolError(f"reply_code {r} is not INVALID, SUCCESS or FAILURE")
    header = Header(t, c, r)
    raw = packet[12:]
    cls = _body_class(header)
    if cls is None:
        return header, bytes(raw)
    if cls is DummyReply:
        if len(raw) == 0:
            return header, DummyReply(None)
        if len(raw) != 40:
            raise ProtocolError(f"msg_type {t} reply body is {len(raw)} bytes, expected 0 or 40")
        return header, DummyReply(_fmt(_F * 10, byteorder).unpack(raw))
    if cls is Ping and c == CommType.SERVICE_REPLY and len(raw) == 0:
        return header, Ping()
    fmt = _fmt(_LAYOUTS[cls], byteorder)
    if len(raw) != fmt.size:
        raise ProtocolError(f"msg_type {t} body is {len(raw)} bytes, expected {fmt.size}")
    v = fmt.unpack(raw)
    if cls is Ping:
        return header, Ping(tuple(v))
    if cls is JointPosition:
        return header, JointPosition(v[0], v[1:11])
    if cls is JointTrajPt:
        return header, JointTrajPt(v[0], v[1:11], v[11], v[12])
    if cls is Status:
        return header, Status(*v)
    if cls is JointTrajPtFull:
        return header, JointTrajPtFull(v[0], v[1], v[2], v[3], v[4:14], v[14:24], v[24:34])
    return header, JointFeedback(v[0], v[1], v[2], v[3:13], v[13:23], v[23:33])


class FrameDecoder:
    """Incremental decoder: feed bytes as they arrive, get complete messages out.

    A length outside [12, MAX_LENGTH] means the stream is out of sync (there are no sync bytes
    in the protocol): ProtocolError, and the caller must reconnect.
    """

    def __init__(self, byteorder: str = "big", max_length: int = MAX_LENGTH) -> None:
        self.byteorder = byteorder
        self.max_length = max_length
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[tuple[Header, Body | bytes]]:
        self._buf += data
        out = []
        lfmt = _fmt(_I, self.byteorder)
        while len(self._buf) >= 4:
            (length,) = lfmt.unpack_from(self._buf)
            if not 12 <= length <= self.max_length:
                raise ProtocolError(f"length prefix {length} outside [12, {self.max_length}]: "
                                    "stream out of sync")
            if len(self._buf) < 4 + length:
                break
            packet = bytes(self._buf[4 : 4 + length])
            del self._buf[: 4 + length]
            out.append(decode_packet(packet, self.byteorder))
        return out

    @property
    def pending(self) -> int:
        """Bytes of an incomplete packet held back."""
        return len(self._buf)
