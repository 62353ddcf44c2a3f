"""Encoders and decoders for every message type on the bus. Pure: no I/O.

Images, point clouds, transforms, joint states and logs are Foxglove well-known schemas in
protobuf; commands, status, events and results are JSON with a JSON Schema from
``protocols/schemas/``.
"""

from __future__ import annotations

import json
import time
from functools import cache
from importlib import resources
from typing import Any

import numpy as np
from foxglove_schemas_protobuf import (
    CompressedImage_pb2,
    FrameTransform_pb2,
    JointStates_pb2,
    Log_pb2,
    PackedElementField_pb2,
    PointCloud_pb2,
    PoseInFrame_pb2,
    RawImage_pb2,
)
from google.protobuf.message import DecodeError, Message
from google.protobuf.timestamp_pb2 import Timestamp
from mcap_protobuf.schema import build_file_descriptor_set
from scancell.protocols.encoding import JSON, PROTOBUF, Encoded, EncodingError, split_encoding

PROTO_CLASSES: dict[str, type[Message]] = {
    cls.DESCRIPTOR.full_name: cls
    for cls in (
        RawImage_pb2.RawImage,
        CompressedImage_pb2.CompressedImage,
        PointCloud_pb2.PointCloud,
        FrameTransform_pb2.FrameTransform,
        PoseInFrame_pb2.PoseInFrame,
        JointStates_pb2.JointStates,
        Log_pb2.Log,
    )
}


def now_ns() -> int:
    """Host clock, UTC, int nanoseconds."""
    return time.time_ns()


def _stamp(ns: int) -> Timestamp:
    ts = Timestamp()
    ts.FromNanoseconds(int(ns))
    return ts


# ---------------------------------------------------------------- JSON


@cache
def json_schema(name: str) -> dict[str, Any]:
    """The JSON Schema named ``name`` (e.g. ``scancell.DeviceStatus``), from protocols/schemas."""
    path = resources.files("scancell.protocols") / "schemas" / f"{name}.json"
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise EncodingError(f"no JSON Schema named {name!r} in scancell/protocols/schemas") from None


def json_schema_names() -> list[str]:
    folder = resources.files("scancell.protocols") / "schemas"
    return sorted(p.name[: -len(".json")] for p in folder.iterdir() if p.name.endswith(".json"))


def encode_json(obj: Any, schema: str) -> Encoded:
    """JSON-encode ``obj`` as a message of JSON Schema ``schema``."""
    return Encoded(json.dumps(obj, separators=(",", ":")).encode(), JSON, schema)


def encode_proto(msg: Message) -> Encoded:
    return Encoded(msg.SerializeToString(), PROTOBUF, msg.DESCRIPTOR.full_name)


def decode(payload: bytes, encoding: str) -> Any:
    """Decode a payload by its encoding string: a dict for JSON, a protobuf message otherwise."""
    mime, schema = split_encoding(encoding)
    if mime == JSON:
        try:
            return json.loads(payload)
        except ValueError as exc:
            raise EncodingError(f"{schema}: payload is not JSON: {exc}") from None
    cls = PROTO_CLASSES.get(schema)
    if cls is None:
        raise EncodingError(f"unknown protobuf schema {schema!r}")
    msg = cls()
    try:
        msg.ParseFromString(bytes(payload))
    except DecodeError as exc:
        raise EncodingError(f"{schema}: payload is not a valid message: {exc}") from None
    return msg


def schema_data(mime: str, schema: str) -> bytes:
    """The schema bytes a self-describing file (MCAP) needs for this encoding.

    Protobuf: a serialized FileDescriptorSet; JSON: the JSON Schema document.
    """
    if mime == PROTOBUF:
        cls = PROTO_CLASSES.get(schema)
        if cls is None:
            raise EncodingError(f"unknown protobuf schema {schema!r}")
        return build_file_descriptor_set(cls).SerializeToString()
    if mime == JSON:
        return json.dumps(json_schema(schema)).encode()
    raise EncodingError(f"unknown mime type {mime!r}")


# ---------------------------------------------------------------- Foxglove builders


def raw_image(image: np.ndarray, stamp_ns: int, frame_id: str) -> RawImage_pb2.RawImage:
    """A mono8/mono16/rgb8 image as foxglove.RawImage."""
    img = np.ascontiguousarray(image)
    if img.ndim == 2 and img.dtype == np.uint8:
        enc, channels = "mono8", 1
    elif img.ndim == 2 and img.dtype == np.uint16:
        enc, channels = "mono16", 1
    elif img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
        enc, channels = "rgb8", 3
    else:
        raise EncodingError(f"unsupported image {img.shape} {img.dtype}")
    return RawImage_pb2.RawImage(
        timestamp=_stamp(stamp_ns),
        frame_id=frame_id,
        width=img.shape[1],
        height=img.shape[0],
        encoding=enc,
        step=img.shape[1] * channels * img.itemsize,
        data=img.tobytes(),
    )


def image_array(msg: RawImage_pb2.RawImage) -> np.ndarray:
    """Inverse of :func:`raw_image`."""
    dtypes = {"mono8": (np.uint8, 1), "mono16": (np.uint16, 1), "rgb8": (np.uint8, 3)}
    if msg.encoding not in dtypes:
        raise EncodingError(f"unsupported RawImage encoding {msg.encoding!r}")
    dtype, ch = dtypes[msg.encoding]
    item = np.dtype(dtype).itemsize
    if msg.step != msg.width * ch * item or len(msg.data) != msg.step * msg.height:
        raise EncodingError(
            f"RawImage {msg.width}x{msg.height} {msg.encoding}: "
            f"step {msg.step} / data {len(msg.data)} bytes inconsistent"
        )
    arr = np.frombuffer(msg.data, dtype=dtype)
    shape = (msg.height, msg.width) if ch == 1 else (msg.height, msg.width, ch)
    return arr.reshape(shape)


_F32 = PackedElementField_pb2.PackedElementField.FLOAT32


def point_cloud(
    points_mm: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    extra: dict[str, np.ndarray] | None = None,
) -> PointCloud_pb2.PointCloud:
    """An (N, 3) cloud in mm as foxglove.PointCloud with float32 x, y, z and optional fields.

    Foxglove's 3D panel takes the values as they are; the frame's unit is mm throughout scancell.
    """
    pts = np.asarray(points_mm, dtype=np.float32).reshape(-1, 3)
    names = ["x", "y", "z"]
    columns = [pts[:, 0], pts[:, 1], pts[:, 2]]
    for name, values in (extra or {}).items():
        values = np.asarray(values, dtype=np.float32).reshape(-1)
        if values.shape[0] != pts.shape[0]:
            raise EncodingError(f"field {name!r} has {values.shape[0]} values for {len(pts)} points")
        names.append(name)
        columns.append(values)
    packed = np.stack(columns, axis=1).astype("<f4")
    fields = [
        PackedElementField_pb2.PackedElementField(name=n, offset=4 * i, type=_F32)
        for i, n in enumerate(names)
    ]
    return PointCloud_pb2.PointCloud(
        timestamp=_stamp(stamp_ns),
        frame_id=frame_id,
        point_stride=4 * len(names),
        fields=fields,
        data=packed.tobytes(),
    )


def cloud_fields(msg: PointCloud_pb2.PointCloud) -> dict[str, np.ndarray]:
    """Inverse of :func:`point_cloud` for float32 fields: name -> (N,) array."""
    stride = msg.point_stride
    if stride <= 0 or len(msg.data) % stride:
        raise EncodingError(f"PointCloud data of {len(msg.data)} bytes is not a multiple of {stride}")
    raw = np.frombuffer(msg.data, dtype=np.uint8).reshape(-1, stride)
    out: dict[str, np.ndarray] = {}
    for f in msg.fields:
        if f.type != _F32 or f.offset + 4 > stride:
            raise EncodingError(f"PointCloud field {f.name!r}: only float32 inside the stride")
        out[f.name] = raw[:, f.offset : f.offset + 4].copy().view("<f4").reshape(-1)
    return out


def cloud_points(msg: PointCloud_pb2.PointCloud) -> np.ndarray:
    f = cloud_fields(msg)
    try:
        return np.stack([f["x"], f["y"], f["z"]], axis=1)
    except KeyError as exc:
        raise EncodingError(f"PointCloud has no field {exc}") from None


def frame_transform(
    T_parent_from_child: np.ndarray, stamp_ns: int, parent: str, child: str
) -> FrameTransform_pb2.FrameTransform:
    """A 4x4 homogeneous transform (mm) as foxglove.FrameTransform (child pose in parent)."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(T_parent_from_child, dtype=float)
    if T.shape != (4, 4):
        raise EncodingError(f"transform must be 4x4, got {T.shape}")
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    msg = FrameTransform_pb2.FrameTransform(
        timestamp=_stamp(stamp_ns), parent_frame_id=parent, child_frame_id=child
    )
    msg.translation.x, msg.translation.y, msg.translation.z = (float(v) for v in T[:3, 3])
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = x, y, z, w
    return msg


def transform_matrix(msg: FrameTransform_pb2.FrameTransform) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    r = msg.rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()
    T[:3, 3] = [msg.translation.x, msg.translation.y, msg.translation.z]
    return T


def joint_states(names: list[str], positions_rad: np.ndarray, stamp_ns: int):
    """Joint positions (rad) as foxglove.JointStates."""
    msg = JointStates_pb2.JointStates(timestamp=_stamp(stamp_ns))
    for n, q in zip(names, np.asarray(positions_rad, dtype=float), strict=True):
        msg.joints.add(name=n, position=float(q))
    return msg


LOG_LEVELS = {"DEBUG": 1, "INFO": 2, "WARNING": 3, "ERROR": 4, "CRITICAL": 5}


def log_message(level: str, message: str, name: str, stamp_ns: int) -> Log_pb2.Log:
    return Log_pb2.Log(
        timestamp=_stamp(stamp_ns), level=LOG_LEVELS.get(level, 0), message=message, name=name
    )
