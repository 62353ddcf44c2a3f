"""Markdown pages of every bus key and message schema, from ``protocols/keys.py`` and the JSON
Schemas in ``protocols/schemas/``."""

from __future__ import annotations

from itertools import groupby
from typing import Any

from scancell.docsgen.markdown import cell, json_type

GROUP_TITLES = {
    "commands": "Commands", "devices": "Devices and the daemon", "jobs": "Jobs",
    "scans": "Scans", "calibrations": "Calibrations", "fusion": "Fusion: the fused cloud",
    "inspection": "Inspection", "acceptance": "Acceptance", "recording": "Recording",
    "workers": "Workers",
}


#: the kinds whose operations are ``cmd/device/<name>/<op>`` (devices/base.py; ``sim`` and
#: ``mock``: the simulator's and the mock devices' test operations)
DEVICE_KINDS = {"axis", "camera", "projector", "robot", "tracker", "sim", "mock"}


def _schema_link(schema: str, depth: str = "../") -> str:
    """A link to a message page for each ``scancell.*`` schema named in ``schema``."""
    out = []
    for word in schema.replace("->", " -> ").split():
        if word.startswith("scancell.") and not word.startswith("scancell.cmd."):
            out.append(f"[`{word}`]({depth}messages/{word}.md)")
        elif word.startswith("foxglove."):
            name = word.removeprefix("foxglove.")
            out.append(f"[`{word}`](https://docs.foxglove.dev/docs/sdk/schemas/"
                       f"{''.join('-' + c.lower() if c.isupper() else c for c in name).lstrip('-')})")
        elif word.startswith("scancell.cmd."):
            out.append(f"[`{word}`]({depth}commands.md)")
        else:
            out.append(word)
    return " ".join(out)


def key_pages() -> dict[str, str]:
    from scancell.protocols.keys import KEY_CATALOGUE, ROOT

    out: dict[str, str] = {}
    index = ["# Bus keys", "",
             f"Every key expression of a cell, under `{ROOT}/<cell>/`, generated from "
             "`protocols/keys.py` when the site is built. Every sample carries its zenoh encoding "
             "`<mime>;<schema>` and an attachment with its acquisition time (int ns, UTC), its "
             "sequence number and its tags.", "",
             "| group | keys |", "|---|---|"]
    ordered = sorted(KEY_CATALOGUE, key=lambda k: list(GROUP_TITLES).index(k.group))
    for group, docs in groupby(ordered, key=lambda k: k.group):
        docs = list(docs)
        index.append(f"| [{GROUP_TITLES[group]}]({group}.md) | "
                     + ", ".join(f"`{d.key}`" for d in docs) + " |")
        page = [f"# {GROUP_TITLES[group]}", "",
                f"Keys under `{ROOT}/<cell>/`. Kinds: *sample* (a put), *latched* (a put, and a "
                "queryable answering with the last one), *query* (a queryable), *liveliness* (a "
                "token).", ""]
        for d in docs:
            page += [f"## `{d.key}`", "",
                     f"- **full key:** `{ROOT}/<cell>/{d.key}`",
                     f"- **kind:** {d.kind}",
                     f"- **message:** {_schema_link(d.schema) if d.schema else '—'}",
                     f"- **published by:** {d.publisher}", "", d.doc[0].upper() + d.doc[1:] + ".", ""]
        out[f"reference/bus/{group}.md"] = "\n".join(page)
    out["reference/bus/index.md"] = "\n".join(index) + "\n"
    return out


def schema_markdown(name: str, schema: dict[str, Any], title_level: int = 1) -> str:
    head = "#" * title_level
    out = [f"{head} `{name}`", ""]
    if schema.get("description"):
        out += [cell(schema["description"]), ""]
    props = schema.get("properties", {})
    required = set(schema.get("required", ()))
    if props:
        out += ["| field | type | required | what |", "|---|---|---|---|"]
        for key, prop in props.items():
            out.append(f"| `{key}` | {cell(json_type(prop))} | {'yes' if key in required else ''} | "
                       f"{cell(prop.get('description', ''))} |")
        out.append("")
    return "\n".join(out)


def message_pages() -> dict[str, str]:
    from scancell.protocols.keys import KEY_CATALOGUE
    from scancell.protocols.messages import json_schema, json_schema_names

    out: dict[str, str] = {}
    used: dict[str, list[str]] = {}
    for d in KEY_CATALOGUE:
        for word in d.schema.split():
            used.setdefault(word, []).append(d.key)
    index = ["# Messages", "",
             "The JSON messages (`application/json;scancell.<Name>`), each validated by its JSON "
             "Schema in `protocols/schemas/`, which MCAP recordings also carry. Foxglove's own "
             "(`foxglove.PointCloud`, `RawImage`, ...) are protobuf, as the Foxglove app reads them.",
             "", "| message | on | what |", "|---|---|---|"]
    commands = ["# Commands", "",
                "Every command the daemon answers on `cmd/<verb>`: its request's JSON Schema "
                "(`protocols/schemas/scancell.cmd.*.json`). The reply is `scancell.CommandReply`. "
                "Device operations are `cmd/device/<name>/<op>`, validated by the schema of "
                "`<kind>.<op>`.", ""]
    for name in json_schema_names():
        schema = json_schema(name)
        if name.startswith("scancell.cmd."):
            verb = name.removeprefix("scancell.cmd.").replace(".", "/")
            kind, _, op = verb.partition("/")
            if kind in DEVICE_KINDS and op:
                verb = f"device/<{kind}>/{op}"
            commands.append(schema_markdown(f"cmd/{verb}", schema, 2))
            continue
        out[f"reference/messages/{name}.md"] = schema_markdown(name, schema)
        keys = ", ".join(f"`{k}`" for k in used.get(name, [])) or "attachments, recordings"
        index.append(f"| [`{name}`]({name}.md) | {keys} | {cell(schema.get('description', ''))} |")
    out["reference/messages/index.md"] = "\n".join(index) + "\n"
    out["reference/commands.md"] = "\n".join(commands)
    return out


def pages() -> dict[str, str]:
    return {**key_pages(), **message_pages()}
