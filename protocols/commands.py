"""The command envelope: JSON requests validated by JSON Schema, JSON replies. Pure: no I/O.

A reply is ``{"result": {...}}`` on success or ``{"error": {"code": ..., "message": ...}}``.
"""

from __future__ import annotations

import json
from functools import cache
from typing import Any

from scancell.protocols.messages import json_schema

REPLY_SCHEMA = "scancell.CommandReply"

#: Every error code a command can answer with, and what it means.
ERROR_CODES: dict[str, str] = {
    "bad_request": "the payload is not a JSON object",
    "invalid": "the request does not match the command's JSON Schema",
    "unknown_command": "no such command",
    "unknown_device": "no device of that name in this cell",
    "out_of_range": "a value is outside a configured limit",
    "device_unavailable": "the device is not connected (it may be reconnecting)",
    "connection_lost": "the link to the device dropped during the command",
    "timeout": "the command or the device did not finish in time",
    "device_fault": "the device reported a fault",
    "bad_reply": "the device answered with something that could not be understood",
    "busy": "another command or job holds the resource",
    "aborted": "the command was aborted (shutdown, stop or estop)",
    "calibration_failed": "a calibration's measurements gave no result (the previous one is kept)",
    "not_settled": "the tracker's readings kept moving: the arm did not settle in time",
    "nest_check_failed": "the reference nests could not locate the tracker (out of sight, or "
                         "they disagree beyond the tolerance)",
    "internal": "a bug in scancell: please report it with the daemon log",
}


class CommandError(Exception):
    """A command failed with one of :data:`ERROR_CODES`."""

    def __init__(self, code: str, message: str) -> None:
        if code not in ERROR_CODES:
            raise ValueError(f"unknown error code {code!r}")
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


def request_schema_name(verb: str) -> str:
    """Schema name of a command's request, e.g. ``status`` -> ``scancell.cmd.status``."""
    return "scancell.cmd." + verb.replace("/", ".")


@cache
def _validator(schema_name: str):
    import jsonschema

    schema = json_schema(schema_name)
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema)


def validate(obj: Any, schema_name: str, what: str = "request") -> None:
    """Raise CommandError('invalid', ...) naming the first offending field."""
    errors = sorted(_validator(schema_name).iter_errors(obj), key=lambda e: list(e.path))
    if errors:
        err = errors[0]
        where = "/" + "/".join(str(p) for p in err.path) if err.path else "(top level)"
        raise CommandError("invalid", f"{what} field {where}: {err.message}")


def parse_request(payload: bytes | None, schema_name: str) -> dict[str, Any]:
    """Decode and validate a request payload; an empty payload means ``{}``."""
    if not payload:
        obj: Any = {}
    else:
        try:
            obj = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as exc:
            raise CommandError("bad_request", f"payload is not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise CommandError("bad_request", f"payload must be a JSON object, got {type(obj).__name__}")
    validate(obj, schema_name)
    return obj


def ok_reply(result: Any) -> dict[str, Any]:
    return {"result": result}


def error_reply(code: str, message: str) -> dict[str, Any]:
    return {"error": {"code": code, "message": message}}


def unwrap_reply(reply: Any) -> Any:
    """The result of a reply object, or raise the CommandError it carries."""
    if not isinstance(reply, dict) or ("result" in reply) == ("error" in reply):
        raise CommandError("bad_reply", f"reply is neither a result nor an error: {reply!r:.200}")
    if "error" in reply:
        err = reply["error"]
        code = err.get("code", "internal") if isinstance(err, dict) else "internal"
        msg = err.get("message", str(err)) if isinstance(err, dict) else str(err)
        raise CommandError(code if code in ERROR_CODES else "internal", msg)
    return reply["result"]
