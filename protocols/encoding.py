"""How a sample on the bus says what it is: encoding, schema name and acquisition stamp.

Every sample carries a zenoh Encoding ``<mime>;<schema>`` (``application/json;scancell.DeviceStatus``,
``application/protobuf;foxglove.RawImage``) and an attachment with its acquisition time, so that
a generic subscriber (the recorder, a replay) needs no knowledge of the type.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

JSON = "application/json"
PROTOBUF = "application/protobuf"
MIME_TYPES = (JSON, PROTOBUF)

#: MCAP names of the message and schema encodings for each mime type.
MCAP_MESSAGE_ENCODING = {JSON: "json", PROTOBUF: "protobuf"}
MCAP_SCHEMA_ENCODING = {JSON: "jsonschema", PROTOBUF: "protobuf"}


class EncodingError(ValueError):
    """A sample's encoding, attachment or payload could not be understood."""


@dataclass(frozen=True)
class Encoded:
    """A payload ready for the bus: bytes plus mime type and schema name."""

    payload: bytes
    mime: str
    schema: str

    @property
    def encoding(self) -> str:
        """The zenoh encoding string, ``<mime>;<schema>``."""
        return f"{self.mime};{self.schema}"


def split_encoding(encoding: str) -> tuple[str, str]:
    """Split a zenoh encoding string into (mime, schema); raises EncodingError if unusable."""
    mime, sep, schema = str(encoding).partition(";")
    if mime not in MIME_TYPES or not sep or not schema:
        raise EncodingError(
            f"encoding {encoding!r} is not '<mime>;<schema>' with mime one of {MIME_TYPES}"
        )
    return mime, schema


@dataclass(frozen=True)
class Attachment:
    """Per-sample metadata: acquisition time (int ns, UTC, host clock), sequence and extras.

    ``device_stamp_ns`` is the device's own clock where the device has one.
    ``meta`` holds small string/number fields that let a recording trace a sample to its job,
    station and pattern index.
    """

    stamp_ns: int
    seq: int = 0
    device_stamp_ns: int | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def to_bytes(self) -> bytes:
        obj: dict[str, Any] = {"stamp_ns": self.stamp_ns, "seq": self.seq}
        if self.device_stamp_ns is not None:
            obj["device_stamp_ns"] = self.device_stamp_ns
        if self.meta:
            obj["meta"] = self.meta
        return json.dumps(obj, separators=(",", ":")).encode()

    @classmethod
    def from_bytes(cls, data: bytes | None) -> Attachment:
        if not data:
            raise EncodingError("sample has no attachment (expected stamp_ns and seq)")
        try:
            obj = json.loads(data)
            stamp = obj["stamp_ns"]
            seq = obj.get("seq", 0)
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise EncodingError(f"bad attachment {data[:80]!r}: {exc}") from None
        if not isinstance(stamp, int) or not isinstance(seq, int):
            raise EncodingError(f"bad attachment {data[:80]!r}: stamp_ns and seq must be ints")
        meta = obj.get("meta") or {}
        if not isinstance(meta, dict):
            raise EncodingError(f"bad attachment {data[:80]!r}: meta must be an object")
        return cls(stamp, seq, obj.get("device_stamp_ns"), meta)
