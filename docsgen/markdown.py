"""Small pieces every generated page uses: a table cell, and a JSON Schema property's type."""

from __future__ import annotations

import json
from typing import Any


def cell(text: Any) -> str:
    """``text`` on one line, safe inside a Markdown table cell."""
    return " ".join(str(text).split()).replace("|", "\\|")


def json_type(prop: dict[str, Any]) -> str:
    """A JSON Schema property's type as a reader says it: ``number (> 0)``, ``one of "a", "b"``,
    ``array of integer``, a ``$ref``'s name."""
    if "$ref" in prop:
        return prop["$ref"].rsplit("/", 1)[-1]
    if "enum" in prop:
        return "one of " + ", ".join(json.dumps(v) for v in prop["enum"])
    if "const" in prop:
        return json.dumps(prop["const"])
    for combo in ("oneOf", "anyOf"):
        if combo in prop:
            return " or ".join(json_type(p) for p in prop[combo])
    kind = prop.get("type", "any")
    kind = " or ".join(kind) if isinstance(kind, list) else kind
    if isinstance(prop.get("items"), dict):
        return f"array of {json_type(prop['items'])}"
    limits = [f"{op} {prop[k]}" for k, op in (("minimum", "≥"), ("exclusiveMinimum", ">"),
                                             ("maximum", "≤"), ("exclusiveMaximum", "<"))
              if k in prop]
    return kind + (f" ({', '.join(limits)})" if limits else "")
