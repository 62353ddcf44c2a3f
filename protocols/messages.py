"""Encoders and decoders for every message type on the bus. Pure: no I/O.

Commands, status, events and results are JSON with a JSON Schema from ``protocols/schemas/``
(here). Images, point clouds, transforms, joint states and logs are Foxglove well-known schemas
in protobuf (``protocols/foxglove_schemas.py``, loaded only when a protobuf message is met).
"""

from __future__ import annotations

import json
import time
from functools import cache
from importlib import resources
from typing import Any

from scancell.protocols.encoding import JSON, PROTOBUF, Encoded, EncodingError, split_encoding


def now_ns() -> int:
    """Host clock, UTC, int nanoseconds."""
    return time.time_ns()


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
    """JSON-encode ``obj`` as a message of JSON Schema ``schema``. A top-level ``stamp_ns``
    (int ns, about 1.8e18) also goes out as ``stamp: {sec, nsec}``, Foxglove's time, which a
    JavaScript viewer reads exactly (its numbers are exact only up to 2^53)."""
    if isinstance(obj, dict) and isinstance(obj.get("stamp_ns"), int) and "stamp" not in obj:
        sec, nsec = divmod(obj["stamp_ns"], 1_000_000_000)
        obj = {**obj, "stamp": {"sec": sec, "nsec": nsec}}
    return Encoded(json.dumps(obj, separators=(",", ":")).encode(), JSON, schema)


def decode(payload: bytes, encoding: str) -> Any:
    """Decode a payload by its encoding string: a dict for JSON, a protobuf message otherwise."""
    mime, schema = split_encoding(encoding)
    if mime == JSON:
        try:
            return json.loads(payload)
        except ValueError as exc:
            raise EncodingError(f"{schema}: payload is not JSON: {exc}") from None
    from scancell.protocols.foxglove_schemas import decode_proto

    return decode_proto(payload, schema)


def schema_data(mime: str, schema: str) -> bytes:
    """The schema bytes a self-describing file (MCAP) needs for this encoding.

    Protobuf: a serialized FileDescriptorSet; JSON: the JSON Schema document.
    """
    if mime == PROTOBUF:
        from scancell.protocols.foxglove_schemas import file_descriptor_set

        return file_descriptor_set(schema)
    if mime == JSON:
        return json.dumps(json_schema(schema)).encode()
    raise EncodingError(f"unknown mime type {mime!r}")
