"""Markdown pages of every cell-config key with its type, default and unit, from the config
model: the dataclasses that hold a table, the :class:`KeySpec` tables the parsers check, and the
JSON Schemas of the drivers' options and of ``[simulator]``."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
from dataclasses import dataclass
from typing import Any

from scancell.docsgen.markdown import cell, json_type
from scancell.model.config_keys import REQUIRED, KeySpec

#: a key's unit from the end of its name (README: mm, s, degrees for people)
UNIT_SUFFIXES = (("_mm_s", "mm/s"), ("_mm", "mm"), ("_us", "µs"), ("_s", "s"), ("_deg", "°"),
                 ("_ppm", "ppm"), ("_mb", "MiB"), ("_bytes", "bytes"), ("_px", "px"),
                 ("_dn", "DN"), ("_hpa", "hPa"), ("_c", "°C"), ("_pct", "%"), ("_hz", "Hz"))


def unit_of(name: str) -> str:
    return next((unit for suffix, unit in UNIT_SUFFIXES if name.endswith(suffix)), "")


@dataclass(frozen=True)
class Table:
    """One table of a cell config and where its keys are defined."""

    name: str
    doc: str
    keys: dict[str, KeySpec]
    source: str
    #: the section's heading; default: the table's name in brackets
    heading: str = ""


def _field_docs(cls: type) -> dict[str, str]:
    """Each field's ``#:`` comment above it, or its trailing ``# ...`` comment."""
    src = textwrap.dedent(inspect.getsource(cls))
    lines = src.splitlines()
    out: dict[str, str] = {}
    for node in ast.parse(src).body[0].body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            i = node.lineno - 1
            above: list[str] = []
            j = i - 1
            while j >= 0 and lines[j].strip().startswith("#:"):
                above.insert(0, lines[j].strip()[2:].strip())
                j -= 1
            trailing = lines[node.end_lineno - 1].split("  # ", 1)
            text = " ".join(above) or (trailing[1].strip() if len(trailing) == 2 else "")
            out[node.target.id] = text.replace("``", "`")
    return out


def from_dataclass(cls: type, skip: tuple[str, ...] = ()) -> dict[str, KeySpec]:
    """The keys of a table a dataclass holds: its fields, their annotations and defaults."""
    docs = _field_docs(cls)
    out: dict[str, KeySpec] = {}
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = REQUIRED
        if dataclasses.is_dataclass(default):
            continue  # a nested table, documented on its own
        out[f.name] = KeySpec(str(f.type), docs.get(f.name, ""), default, unit_of(f.name))
    return out


def from_json_schema(schema: dict[str, Any], prefix: str = "") -> dict[str, KeySpec]:
    """The keys a JSON Schema's properties allow (nested objects as ``table.key``)."""
    required = set(schema.get("required", ()))
    out: dict[str, KeySpec] = {}
    for name, prop in schema.get("properties", {}).items():
        key = prefix + name
        if prop.get("type") == "object" and "properties" in prop:
            out.update(from_json_schema(prop, key + "."))
            continue
        out[key] = KeySpec(json_type(prop), prop.get("description", ""),
                           REQUIRED if name in required else prop.get("default"), unit_of(name))
    return out


def tables() -> list[Table]:
    """Every table of a cell config, in the order a config file usually has them."""
    from scancell import config
    from scancell.analysis.decode_limits import DecodeLimits
    from scancell.bus.zenoh_bus import BUS_KEYS, BusConfig
    from scancell.config import DaemonConfig
    from scancell.model.cell_geometry import PLANNER_KEYS
    from scancell.model.metrology_settings import MetrologySettings, ScannerCheck
    from scancell.recorder.recorder import RecorderSettings
    from scancell.recorder.session_file import FileSettings

    bus = from_dataclass(BusConfig)
    bus["password_file"] = BUS_KEYS["password_file"]
    bus["tls"] = BUS_KEYS["tls"]
    recorder = {"enabled": KeySpec("bool", "record inside the daemon; a `[recorder]` table with "
                                           "keys is on unless it says false", True),
                **from_dataclass(RecorderSettings), **from_dataclass(FileSettings)}
    return [
        Table("cell", "The cell's name and description.", config.CELL_KEYS, "config.py"),
        Table("bus", "How the daemon joins the zenoh bus (clients: the same keys in a file "
                     "named by `--bus-config`).", bus, "bus/zenoh_bus.py"),
        Table("daemon", "The daemon's periods and timeouts.", from_dataclass(DaemonConfig),
              "config.py"),
        Table("devices.<name>", "Each device: `driver = \"...\"` and that driver's options "
                                "(see the drivers below).",
              {"driver": KeySpec("string", "a driver name from `scancell drivers`", REQUIRED)},
              "config.py"),
        Table("scanner", "How every scan of the cell is taken unless its request says otherwise.",
              config.SCANNER_KEYS, "config.py"),
        Table("scanner.decode_limits", "Overrides of the decoder's limits, each derived from the "
                                       "fringe width and the measured noise when absent.",
              from_dataclass(DecodeLimits), "analysis/decode_limits.py"),
        Table("recorder", "The recorder inside the daemon: one MCAP file per session.",
              recorder, "recorder/recorder.py, recorder/session_file.py"),
        Table("planner", "A real cell's geometry for planning and the scan job.", PLANNER_KEYS,
              "model/cell_geometry.py"),
        Table("metrology", "The metrology defences: weather, settle detection, reference nests.",
              from_dataclass(MetrologySettings, skip=("scanner_check",)),
              "model/metrology_settings.py"),
        Table("metrology.scanner_check", "A calibrated ball bar fixed in the cell, scanned at "
                                         "the job's start and every `every` stations.",
              from_dataclass(ScannerCheck), "model/metrology_settings.py"),
        Table("inspection", "What the inspect worker compares each fused model with.",
              config.INSPECTION_KEYS, "config.py"),
        Table("acceptance", "The VDI/VDE 2634 acceptance test: volume, artefacts, MPEs.",
              config.ACCEPTANCE_KEYS, "config.py"),
        Table("simulator", "The embedded simulated cell (simulation only).", _simulator_keys(),
              "sim/host.py"),
    ]


def _simulator_keys() -> dict[str, KeySpec]:
    from scancell.sim.host import SIMULATOR_SCHEMA

    return from_json_schema(SIMULATOR_SCHEMA)


def driver_tables() -> list[Table]:
    """Each known driver's options, from its ``OPTIONS_SCHEMA``."""
    from scancell.devices.registry import available_drivers, load_driver

    out = []
    for name, target in sorted(available_drivers().items()):
        cls = load_driver(name)
        doc = (cls.__dict__.get("__doc__") or "").strip().split("\n\n", 1)[0].replace("\n", " ")
        out.append(Table("devices.<name>", doc, from_json_schema(cls.OPTIONS_SCHEMA), target,
                         heading=f'`driver = "{name}"`'))
    return out


def _value(v: Any) -> str:
    if v is REQUIRED:
        return "**required**"
    if v is None:
        return ""
    if isinstance(v, str):
        return f'`"{v}"`'
    if isinstance(v, bool):
        return f"`{str(v).lower()}`"
    if isinstance(v, tuple):
        v = list(v)
    return f"`{v}`"


def table_markdown(t: Table, level: int = 2) -> str:
    out = [f"{'#' * level} {t.heading or f'`[{t.name}]`'}", "", t.doc, "",
           f"Defined in `{t.source}`.", ""]
    if t.keys:
        out += ["| key | type | default | unit | what |", "|---|---|---|---|---|"]
        out += [f"| `{k}` | {cell(s.type)} | {_value(s.default)} | {s.unit} | {cell(s.doc)} |"
                for k, s in t.keys.items()]
    else:
        out.append("No options.")
    return "\n".join(out) + "\n"


def _slug(name: str) -> str:
    return name.replace(".<name>", "").replace(".", "-")


def pages() -> dict[str, str]:
    """``reference/config/<table>.md`` for each table, the drivers' page and the index."""
    out: dict[str, str] = {}
    index = ["# Cell config", "",
             "A cell is one TOML file (`deploy/cells/*.toml`), validated when it loads: an error "
             "names the file, the table, the key and the problem. These pages are generated "
             "from the config model when the site is built.", "",
             "| table | what |", "|---|---|"]
    all_tables = tables()
    for t in all_tables:
        slug = _slug(t.name)
        subs = [s.name for s in all_tables if s.name.startswith(t.name + ".")]
        extra = ("\nSub-tables: " + ", ".join(f"[`[{s}]`]({_slug(s)}.md)" for s in subs) + ".\n"
                 if subs else "")
        if t.name == "devices.<name>":
            extra = "\nEach driver's options: [Driver options](drivers.md).\n"
        out[f"reference/config/{slug}.md"] = table_markdown(t, 1) + extra
        index.append(f"| [`[{t.name}]`]({slug}.md) | {cell(t.doc)} |")
    drivers = ["# Driver options", "", "Each `[devices.<name>]` table names its `driver`; "
               "these are the options each driver takes, from its `OPTIONS_SCHEMA`.", ""]
    drivers += [table_markdown(t, 2) for t in driver_tables()]
    out["reference/config/drivers.md"] = "\n".join(drivers)
    index.append("| [driver options](drivers.md) | every driver's options |")
    out["reference/config/index.md"] = "\n".join(index) + "\n"
    return out
