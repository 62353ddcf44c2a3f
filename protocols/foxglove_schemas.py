"""Foxglove well-known schemas in protobuf: images, point clouds, transforms, joint states and
logs, built from and read into numpy. Pure: no I/O. Imported only where such messages are made
or read, so a JSON-only client (``scancell ctl``) never loads numpy or protobuf."""

from __future__ import annotations

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
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.message import DecodeError, Message
from google.protobuf.timestamp_pb2 import Timestamp
from scancell.protocols.encoding import PROTOBUF, Encoded, EncodingError

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


def _stamp(ns: int) -> Timestamp:
    ts = Timestamp()
    ts.FromNanoseconds(int(ns))
    return ts


def encode_proto(msg: Message) -> Encoded:
    return Encoded(msg.SerializeToString(), PROTOBUF, msg.DESCRIPTOR.full_name)


def decode_proto(payload: bytes, schema: str) -> Message:
    """A protobuf payload of one of the Foxglove schemas above; raises EncodingError."""
    cls = PROTO_CLASSES.get(schema)
    if cls is None:
        raise EncodingError(f"unknown protobuf schema {schema!r}")
    msg = cls()
    try:
        msg.ParseFromString(bytes(payload))
    except DecodeError as exc:
        raise EncodingError(f"{schema}: payload is not a valid message: {exc}") from None
    return msg


def file_descriptor_set(schema: str) -> bytes:
    """The serialized FileDescriptorSet of a schema and every file it depends on, dependencies
    first: what an MCAP file's protobuf schema record holds."""
    cls = PROTO_CLASSES.get(schema)
    if cls is None:
        raise EncodingError(f"unknown protobuf schema {schema!r}")
    fds, seen = FileDescriptorSet(), set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(cls.DESCRIPTOR.file)
    return fds.SerializeToString()



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


def image_array(msg: RawImage_pb2.RawImage | CompressedImage_pb2.CompressedImage) -> np.ndarray:
    """Inverse of :func:`raw_image` and of :func:`png_image` (any PNG or JPEG CompressedImage:
    mono as 2-D, colour as RGB)."""
    if isinstance(msg, CompressedImage_pb2.CompressedImage):
        return _decoded(msg)
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


def png_image(msg: RawImage_pb2.RawImage) -> CompressedImage_pb2.CompressedImage:
    """A RawImage as a lossless PNG CompressedImage (same stamp and frame): mono8 and mono16
    as grey, rgb8 as colour. The filters are chosen per row (OpenCV's fast filter set) and the
    rows Huffman-coded: 0.30 of a fringe frame's bytes at ~110 MB/s a core, against zlib's
    default strategy's 0.38 at 52 MB/s (benchmarks/bench_recording_size.py)."""
    import cv2

    img = image_array(msg)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)  # OpenCV writes BGR input as RGB
    opts = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FAST_FILTERS,
            cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
    ok, data = cv2.imencode(".png", img, opts)
    if not ok:
        raise EncodingError(f"PNG encoding failed for a {msg.width}x{msg.height} {msg.encoding} image")
    return CompressedImage_pb2.CompressedImage(timestamp=msg.timestamp, frame_id=msg.frame_id,
                                               data=data.tobytes(), format="png")


def _decoded(msg: CompressedImage_pb2.CompressedImage) -> np.ndarray:
    import cv2

    if msg.format.lower() not in ("png", "jpeg", "jpg"):
        raise EncodingError(f"unsupported CompressedImage format {msg.format!r} (png, jpeg)")
    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise EncodingError(f"CompressedImage: {len(msg.data)} bytes are not a {msg.format} image")
    if img.ndim == 2:
        return img
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)


_PEF = PackedElementField_pb2.PackedElementField
#: Foxglove's NumericType -> the little-endian numpy type of its values
_NUMERIC = {_PEF.UINT8: np.dtype("u1"), _PEF.INT8: np.dtype("i1"), _PEF.UINT16: np.dtype("<u2"),
            _PEF.INT16: np.dtype("<i2"), _PEF.UINT32: np.dtype("<u4"), _PEF.INT32: np.dtype("<i4"),
            _PEF.FLOAT32: np.dtype("<f4"), _PEF.FLOAT64: np.dtype("<f8")}
_TYPE_OF = {dtype: numeric for numeric, dtype in _NUMERIC.items()}


def point_cloud(
    points_mm: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    extra: dict[str, np.ndarray] | None = None,
) -> PointCloud_pb2.PointCloud:
    """An (N, 3) cloud in mm as foxglove.PointCloud with float32 x, y, z and optional fields,
    packed without padding. A field of an integer type Foxglove knows (8, 16 or 32 bits)
    keeps its type; any other is float32.

    Foxglove's 3D panel takes the values as they are; the frame's unit is mm throughout scancell.
    """
    pts = np.asarray(points_mm, dtype=np.float32).reshape(-1, 3)
    columns: dict[str, np.ndarray] = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}
    for name, values in (extra or {}).items():
        v = np.asarray(values).reshape(-1)
        if v.dtype.kind not in "iu" or v.dtype.newbyteorder("<") not in _TYPE_OF:
            v = v.astype(np.float32)
        if v.shape[0] != pts.shape[0]:
            raise EncodingError(f"field {name!r} has {v.shape[0]} values for {len(pts)} points")
        columns[name] = v
    rec = np.empty(len(pts), [(n, v.dtype.newbyteorder("<")) for n, v in columns.items()])
    for n, v in columns.items():
        rec[n] = v
    fields = [
        PackedElementField_pb2.PackedElementField(
            name=n, offset=rec.dtype.fields[n][1], type=_TYPE_OF[rec.dtype.fields[n][0]])
        for n in columns
    ]
    return PointCloud_pb2.PointCloud(
        timestamp=_stamp(stamp_ns),
        frame_id=frame_id,
        point_stride=rec.dtype.itemsize,
        fields=fields,
        data=rec.tobytes(),
    )


#: foxglove.PointCloud's ``data`` field (PointCloud.proto: bytes data = 6)
_CLOUD_DATA_FIELD = 6


def _varint(buf: memoryview, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if i >= len(buf) or shift > 63:
            raise EncodingError("foxglove.PointCloud: payload is not a valid message: a "
                                "truncated or overlong varint")
        b = buf[i]
        value |= (b & 0x7F) << shift
        i, shift = i + 1, shift + 7
        if not b & 0x80:
            return value, i


def split_cloud(payload: bytes) -> tuple[PointCloud_pb2.PointCloud, memoryview]:
    """A foxglove.PointCloud payload as its message without ``data``, and ``data`` as a view
    into the payload. protobuf copies a bytes field on parse and again on each read (~90 MB
    each for a full-size station's cloud, measured); the points need neither copy."""
    buf = memoryview(payload).cast("B")
    head = bytearray()
    data = buf[0:0]
    i = 0
    while i < len(buf):
        start = i
        key, i = _varint(buf, i)
        field, wire = key >> 3, key & 7
        if wire == 0:
            _, i = _varint(buf, i)
        elif wire == 1:
            i += 8
        elif wire == 5:
            i += 4
        elif wire == 2:
            n, i = _varint(buf, i)
            if field == _CLOUD_DATA_FIELD and i + n <= len(buf):
                data = buf[i:i + n]  # the last one wins, as protobuf's parse does
                i += n
                continue
            i += n
        else:
            raise EncodingError(f"foxglove.PointCloud: payload is not a valid message: wire "
                                f"type {wire} at byte {start}")
        if i > len(buf):
            raise EncodingError(f"foxglove.PointCloud: payload is not a valid message: field "
                                f"{field} at byte {start} runs past its end")
        head += buf[start:i]
    return decode_proto(bytes(head), "foxglove.PointCloud"), data


def _cloud_records(msg: PointCloud_pb2.PointCloud, data: memoryview | bytes | None = None
                   ) -> np.ndarray:
    """The cloud's data (``msg.data``, or ``data`` from :func:`split_cloud`) as a structured
    array over its bytes (no copy of the values)."""
    stride = msg.point_stride
    if data is None:
        data = msg.data  # one copy out of the message (upb hands out a new bytes object each time)
    if stride <= 0 or len(data) % stride:
        raise EncodingError(f"PointCloud data of {len(data)} bytes is not a multiple of {stride}")
    names, formats, offsets = [], [], []
    for f in msg.fields:
        dtype = _NUMERIC.get(f.type)
        if dtype is None or f.offset + dtype.itemsize > stride:
            raise EncodingError(f"PointCloud field {f.name!r}: type {f.type} at offset "
                                f"{f.offset} is not a number inside the {stride}-byte stride")
        names.append(f.name)
        formats.append(dtype)
        offsets.append(f.offset)
    try:
        layout = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                           "itemsize": stride})
    except ValueError as exc:  # a name twice
        raise EncodingError(f"PointCloud fields {names}: {exc}") from None
    return np.frombuffer(data, layout)


def cloud_fields(msg: PointCloud_pb2.PointCloud, names: list[str] | None = None
                 ) -> dict[str, np.ndarray]:
    """The fields of a foxglove.PointCloud (all, or those of ``names`` it has), of any of its
    numeric types: name -> (N,) array."""
    rec = _cloud_records(msg)
    return {n: rec[n].copy() for n in rec.dtype.names if names is None or n in names}


def cloud_points(msg: PointCloud_pb2.PointCloud) -> np.ndarray:
    """(N, 3) x, y, z of a foxglove.PointCloud, in their own float type (scancell's: float32)."""
    return _xyz(_cloud_records(msg))


def cloud_arrays(msg: PointCloud_pb2.PointCloud | bytes, names: list[str] | None = None
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """:func:`cloud_points` and the other fields (all, or those of ``names`` it has) from one
    read of the message's bytes (a full-size station's cloud is ~90 MB of them). Given the
    payload itself, the values are read where they lie in it (:func:`split_cloud`)."""
    rec = _cloud_records(*split_cloud(msg)) if isinstance(msg, bytes | bytearray | memoryview) \
        else _cloud_records(msg)
    return _xyz(rec), {n: rec[n].copy() for n in rec.dtype.names
                       if n not in ("x", "y", "z") and (names is None or n in names)}


def _xyz(rec: np.ndarray) -> np.ndarray:
    missing = [n for n in "xyz" if n not in rec.dtype.names]
    if missing:
        raise EncodingError(f"PointCloud has no field {missing[0]!r}")
    out = np.empty((len(rec), 3), np.result_type(*(rec.dtype[n] for n in "xyz")))
    for i, n in enumerate("xyz"):
        out[:, i] = rec[n]
    return out


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
