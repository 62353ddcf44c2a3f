"""Cell configuration: one TOML file per cell, validated at load.

Every error names the file, the key and the problem, e.g.
``deploy/cells/sim.toml: [devices.robot] driver: unknown driver 'fanuc2'; known: ...``.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import jsonschema
from scancell.bus import BusConfig
from scancell.model.cell_geometry import CellGeometry, GeometryError
from scancell.model.config_keys import REQUIRED, KeySpec
from scancell.model.metrology_settings import check_table
from scancell.protocols.keys import check_name


class ConfigError(ValueError):
    """A cell config is missing, unreadable or invalid."""


@dataclass(frozen=True)
class DeviceConfig:
    name: str
    driver: str
    options: dict[str, Any]


@dataclass(frozen=True)
class DaemonConfig:
    #: how often each device's status is published on dev/<device>/status
    status_period_s: float = 1.0
    #: the first wait before a failed device is connected again (doubled each time)
    reconnect_initial_s: float = 0.5
    #: the longest wait between reconnection attempts
    reconnect_max_s: float = 10.0
    #: the longest a device's connect may take
    connect_timeout_s: float = 10.0
    #: the longest the devices may take to stop and close at shutdown
    shutdown_timeout_s: float = 3.0
    #: Per-operation timeout overrides, ``"<kind>.<op>" -> seconds``.
    timeouts: dict[str, float] = field(default_factory=dict)
    #: The robot's home pose for ``cmd/home`` (degrees); None: cmd/home needs joints_deg.
    home_joints_deg: tuple[float, ...] | None = None


@dataclass(frozen=True)
class CellConfig:
    path: Path | None
    cell: str
    description: str
    bus: BusConfig
    daemon: DaemonConfig
    devices: dict[str, DeviceConfig]
    raw: dict[str, Any]
    #: The embedded simulated cell's ``[simulator]`` table (None: no simulator).
    simulator: dict[str, Any] | None = None
    #: The embedded recorder's ``[recorder]`` table (None: no recorder in the daemon).
    recorder: Any = None
    #: The cell's ``[planner]`` table, parsed (None: the config has none).
    planner: CellGeometry | None = None
    #: ``[scanner]``: how every scan of the cell is taken unless its request says otherwise;
    #: ``exposures_us``: a list of exposure times (HDR) or "auto" (absent: one exposure)
    scanner: dict[str, Any] = field(default_factory=dict)
    #: ``[inspection]`` (INSPECTION_KEYS), paths made absolute; empty: no nominal for the cell
    inspection: dict[str, Any] = field(default_factory=dict)
    #: ``[acceptance]`` (ACCEPTANCE_KEYS); empty: the cell states no acceptance test
    acceptance: dict[str, Any] = field(default_factory=dict)
    #: ``[metrology]``: weather, settle detection, reference nests (daemon/jobs/metrology.py)
    metrology: dict[str, Any] = field(default_factory=dict)

    @cached_property
    def geometry(self) -> CellGeometry | None:
        """The cell's geometry for planning and the scan job: ``[planner]``, else the embedded
        simulator's own, else None."""
        if self.planner is not None or self.simulator is None:
            return self.planner
        from scancell.devices.simulator import load_simulator

        return CellGeometry.from_table(load_simulator().planner_table(self.simulator))

    def redacted(self) -> dict[str, Any]:
        """The config as loaded, without passwords and private keys (for recordings, replies)."""
        def scrub(obj: Any) -> Any:
            if isinstance(obj, dict):
                return {k: "***" if any(w in k for w in ("password", "private_key")) else scrub(v)
                        for k, v in obj.items()}
            if isinstance(obj, list):
                return [scrub(v) for v in obj]
            return obj
        return scrub(self.raw)


#: ``[cell]``
CELL_KEYS: dict[str, KeySpec] = {
    "name": KeySpec("string", "the cell's name: every key expression is under "
                              "`scancell/<name>/`; letters, digits, `_`, `-`", REQUIRED),
    "description": KeySpec("string", "free text, shown by `scancell ctl status`", ""),
}
#: ``[scanner]``: how every scan of the cell is taken unless its request says otherwise
SCANNER_KEYS: dict[str, KeySpec] = {
    "exposures_us": KeySpec("list of 1-6 numbers, or \"auto\"",
                            "exposure times of an HDR scan; \"auto\" picks them from a dark and "
                            "a white preview; absent: one exposure at the camera's setting",
                            None, "µs"),
    "decode_limits": KeySpec("table", "overrides of the decoder's derived limits, key by key: "
                                      "`[scanner.decode_limits]`"),
    "warmup_min": KeySpec("number", "the scanner maker's warm-up time after power-on: "
                                    "`cmd/job/warm_up` waits for it, and the calibration, "
                                    "acceptance and scan jobs warn when they start before it; "
                                    "absent: not known, no warning", None, "min"),
}
#: the decision rules a verdict can follow (scancell.analysis.decision.RULES)
DECISION_RULES = ("iso14253-1", "simple")
#: ``[acceptance]``: the VDI/VDE 2634 test's measuring volume (MCS), the artefacts' calibrated
#: sizes (their certificates) and the MPEs, all mm
ACCEPTANCE_NUMBERS = {"sphere_diameter_mm", "ballbar_length_mm", "ballbar_sphere_diameter_mm"}
#: Part 3 (multiple views), optional: a long ball bar at positions in the tracker frame
ACCEPTANCE_PART3 = {"ballbar3_length_mm", "ballbar3_sphere_diameter_mm", "part3_positions_world",
                    "mpe3_mm"}
ACCEPTANCE_KEYS: dict[str, KeySpec] = {
    "volume_size_mm": KeySpec("3 numbers", "the measuring volume's size x, y, z (MCS)",
                              REQUIRED, "mm"),
    "volume_centre_mm": KeySpec("3 numbers", "the measuring volume's centre (MCS)", REQUIRED,
                                "mm"),
    "plane_size_mm": KeySpec("2 numbers", "the flatness artefact's length and width", REQUIRED,
                             "mm"),
    "sphere_diameter_mm": KeySpec("number", "the sphere's calibrated diameter (certificate)",
                                  REQUIRED, "mm"),
    "ballbar_length_mm": KeySpec("number", "the ball bar's calibrated centre distance",
                                 REQUIRED, "mm"),
    "ballbar_sphere_diameter_mm": KeySpec("number", "the ball bar's spheres' diameter",
                                          REQUIRED, "mm"),
    "positions": KeySpec("table {sphere, ballbar, plane}", "positions per artefact",
                         {"sphere": 10, "ballbar": 7, "plane": 6}),
    "mpe_mm": KeySpec("table {PF, PS, SD, F}", "the maximum permissible errors of Part 2",
                      None, "mm"),
    "test_u_mm": KeySpec("table {PF, PS, SD, F, SD3}", "the test's expanded uncertainty (k = 2) "
                         "per parameter: the artefacts' calibration certificates (sphere form "
                         "and diameter, bar lengths, plane form); absent: 0", None, "mm"),
    "decision_rule": KeySpec('"iso14253-1" | "simple"', "how each figure is judged against its "
                             "MPE with the test's U", "iso14253-1"),
    "mpe_camera_width_px": KeySpec("integer", "the camera width (px) Part 2's MPEs are specified "
                                   "at; a scanner run coarser (binning) scales them by "
                                   "specified / actual width; absent: used as given", None, "px"),
    "ballbar3_length_mm": KeySpec("number", "Part 3: the long ball bar's calibrated length",
                                  None, "mm"),
    "ballbar3_sphere_diameter_mm": KeySpec("number", "Part 3: its spheres' diameter", None, "mm"),
    "part3_positions_world": KeySpec("list of [x, y, z, dx, dy, dz]",
                                     "Part 3: the bar's centre and direction in the tracker "
                                     "frame, one per position", None, "mm"),
    "mpe3_mm": KeySpec("table {SD}", "Part 3's maximum permissible error", None, "mm"),
}
#: ``[inspection]``: what the inspect worker compares each fused model with (paths relative
#: to the config file)
INSPECTION_KEYS: dict[str, KeySpec] = {
    "nominal": KeySpec("path", "the part's CAD (STEP, STL, OBJ, PLY); absent: a job is "
                               "inspected only if its plan names a nominal"),
    "unit": KeySpec("string", "a mesh nominal's unit (mm, m, in); a STEP states its own", "mm"),
    "chordal_mm": KeySpec("number", "the chordal tolerance a STEP is meshed to", 0.01, "mm"),
    "align": KeySpec("\"bestfit\" or \"asmeasured\"", "how the model is aligned to the nominal",
                     "bestfit"),
    "T_world_from_part": KeySpec("4x4 matrix", "the fixture: the part's pose in the tracker "
                                               "frame (where best fit starts)", None, "mm"),
    "tolerance_mm": KeySpec("number", "± tolerance of the whole part", None, "mm"),
    "tolerances": KeySpec("path", "per-region tolerances (TOML: faces, boxes, spheres)"),
    "max_distance_mm": KeySpec("number", "points farther from the nominal are not part of it",
                               5.0, "mm"),
    "decision_rule": KeySpec("\"iso14253-1\" or \"simple\"",
                             "how a verdict accounts for the uncertainty: ISO 14253-1's guard "
                             "bands (pass proven inside the tolerance less U, fail beyond it plus "
                             "U, else not provable), or the tolerance's edge alone",
                             "iso14253-1"),
    "point_sigma_mm": KeySpec("number", "each point's 1-sigma where a model carries none "
                                        "(absent: the model's own scatter about local planes)",
                              None, "mm"),
}
#: every table of a cell config
_TOP_KEYS = {"cell", "bus", "daemon", "devices", "scanner", "simulator", "recorder", "planner",
             "inspection", "acceptance", "metrology"}


def load_cell_config(path: str | Path, overrides: dict[str, Any] | None = None) -> CellConfig:
    """Read and validate a cell config. ``overrides`` are merged over the file's tables."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read cell config: {exc.strerror or exc}") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    for table, values in (overrides or {}).items():
        merge_into(raw.setdefault(table, {}), values)
    return parse_cell_config(raw, str(p), p)


def merge_into(into: dict[str, Any], values: dict[str, Any]) -> None:
    for key, value in values.items():
        if isinstance(value, dict) and isinstance(into.get(key), dict):
            merge_into(into[key], value)
        else:
            into[key] = value


def parse_set_option(text: str) -> dict[str, Any]:
    """``"simulator.robot.motion_port=12000"`` -> nested overrides; the value is read as a
    TOML value (number, bool, string, array) and as a bare string if it is not one."""
    key, sep, value = text.partition("=")
    parts = [k.strip() for k in key.split(".")]
    if not sep or not all(parts):
        raise ConfigError(f"--set {text!r}: expected TABLE.KEY=VALUE, e.g. "
                          f"devices.robot.motion_port=12000")
    try:
        parsed: Any = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value
    out: dict[str, Any] = {parts[-1]: parsed}
    for k in reversed(parts[:-1]):
        out = {k: out}
    return out


def merge_overrides(items: list[str]) -> dict[str, Any]:
    """Several ``--set`` options merged into one override mapping."""
    merged: dict[str, Any] = {}
    for item in items:
        merge_into(merged, parse_set_option(item))
    return merged


def parse_cell_config(raw: dict[str, Any], where: str = "<config>",
                      path: Path | None = None) -> CellConfig:
    def err(key: str, problem: str) -> ConfigError:
        return ConfigError(f"{where}: {key}: {problem}")

    unknown = set(raw) - _TOP_KEYS
    if unknown:
        raise err(sorted(unknown)[0], f"unknown table; expected one of {sorted(_TOP_KEYS)}")

    cell_t = _table(raw, "cell", err)
    unknown = set(cell_t) - CELL_KEYS.keys()
    if unknown:
        raise err("[cell]", f"unknown key {sorted(unknown)[0]!r} (known: {', '.join(CELL_KEYS)})")
    name = cell_t.get("name")
    try:
        check_name("cell", name)
    except ValueError as exc:
        raise err("[cell] name", str(exc)) from None

    bus_t = dict(_table(raw, "bus", err))
    if isinstance(bus_t.get("password_file"), str):  # relative to the cell config, as its paths
        bus_t["password_file"] = str(((path.parent if path else Path()) / bus_t["password_file"])
                                     .resolve())
    try:
        bus = BusConfig.from_mapping(bus_t)
    except (ValueError, TypeError) as exc:
        raise err("[bus]", str(exc)) from None

    d = _table(raw, "daemon", err)
    known_d = set(DaemonConfig.__dataclass_fields__)
    for key, value in d.items():
        if key not in known_d:
            raise err(f"[daemon] {key}", f"unknown key; expected one of {sorted(known_d)}")
        if key == "home_joints_deg":
            if not isinstance(value, list) or len(value) != 6 or not all(
                    isinstance(v, int | float) and not isinstance(v, bool) for v in value):
                raise err("[daemon] home_joints_deg", "must be 6 joint angles in degrees")
            continue
        if key == "timeouts":
            if not isinstance(value, dict) or not all(
                isinstance(v, int | float) and v > 0 for v in value.values()
            ):
                raise err("[daemon] timeouts", "must map '<kind>.<op>' to positive seconds")
        elif not isinstance(value, int | float) or value <= 0:
            raise err(f"[daemon] {key}", f"must be a positive number of seconds, got {value!r}")
    daemon = DaemonConfig(**{k: tuple(float(x) for x in v) if k == "home_joints_deg" else v
                             for k, v in d.items()})

    devs = _table(raw, "devices", err)
    devices: dict[str, DeviceConfig] = {}
    for dev_name, table in devs.items():
        key = f"[devices.{dev_name}]"
        try:
            check_name("device", dev_name)
        except ValueError as exc:
            raise err(key, str(exc)) from None
        if not isinstance(table, dict):
            raise err(key, "must be a table")
        driver = table.get("driver")
        if not isinstance(driver, str):
            raise err(f"{key} driver", "missing: name a driver (see `scancell drivers`)")
        options = {k: v for k, v in table.items() if k != "driver"}
        _check_driver(driver, options, key, err)
        devices[dev_name] = DeviceConfig(dev_name, driver, options)
    simulator = raw.get("simulator")
    if simulator is not None:
        if not isinstance(simulator, dict):
            raise err("[simulator]", "must be a table")
        from scancell.devices.simulator import SimulatorUnavailable, load_simulator

        try:
            problem = load_simulator().check_options(simulator)
        except SimulatorUnavailable as exc:
            raise err("[simulator]", str(exc)) from None
        if problem:
            raise err("[simulator]", problem)
    planner = None
    if raw.get("planner"):
        try:
            planner = CellGeometry.from_table(_table(raw, "planner", err))
        except GeometryError as exc:
            raise err("[planner]", str(exc)) from None
    recorder = None
    rec_t = _table(raw, "recorder", err)
    if rec_t.get("enabled", bool(rec_t)):
        from scancell.recorder.recorder import RecorderSettings

        try:
            recorder = RecorderSettings.from_mapping(rec_t)
        except (ValueError, TypeError) as exc:
            raise err("[recorder]", str(exc)) from None
    scanner = _table(raw, "scanner", err)
    unknown = set(scanner) - SCANNER_KEYS.keys()
    if unknown:
        raise err("[scanner]", f"unknown key {sorted(unknown)[0]!r} (known: "
                               f"{', '.join(SCANNER_KEYS)})")
    limits = scanner.get("decode_limits")
    if limits is not None:
        from scancell.analysis.decode_limits import DecodeLimits

        if not isinstance(limits, dict):
            raise err("[scanner] decode_limits", "must be a table of limits "
                                                 "(docs/how-to/decode-real-captures.md)")
        try:
            DecodeLimits.from_mapping(limits, "decode_limits")
        except (ValueError, TypeError) as exc:
            raise err("[scanner] decode_limits", str(exc)) from None
    warmup = scanner.get("warmup_min")
    if warmup is not None and (not isinstance(warmup, int | float) or isinstance(warmup, bool)
                               or not 0 <= warmup <= 1440):
        raise err("[scanner] warmup_min", f"must be a number of minutes from 0 to 1440, got "
                                          f"{warmup!r}")
    exp = scanner.get("exposures_us")
    if exp is not None and exp != "auto" and not (
            isinstance(exp, list) and 1 <= len(exp) <= 6
            and all(isinstance(e, int | float) and not isinstance(e, bool) and e > 0 for e in exp)):
        raise err("[scanner] exposures_us", f"must be 1 to 6 positive exposure times (µs) or "
                                            f"\"auto\", got {exp!r}")
    return CellConfig(path, name, str(cell_t.get("description", "")), bus, daemon, devices, raw,
                      simulator, recorder, planner, dict(scanner),
                      _inspection(_table(raw, "inspection", err), path, err),
                      _acceptance(_table(raw, "acceptance", err), err),
                      _metrology(_table(raw, "metrology", err), err))


def _metrology(t: dict[str, Any], err) -> dict[str, Any]:
    problem = check_table(t)
    if problem:
        key, _, why = problem.partition(": ")
        raise err(f"[metrology] {key}", why)
    return dict(t)


def _acceptance(t: dict[str, Any], err) -> dict[str, Any]:
    if not t:
        return {}
    unknown = set(t) - ACCEPTANCE_KEYS.keys()
    if unknown:
        raise err("[acceptance]", f"unknown key {sorted(unknown)[0]!r} (known: "
                                  f"{', '.join(sorted(ACCEPTANCE_KEYS))})")
    missing = sorted(k for k, spec in ACCEPTANCE_KEYS.items()
                     if spec.default is REQUIRED and k not in t)
    if missing:
        raise err("[acceptance]", f"missing {', '.join(missing)}")

    def positive(v: Any) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool) and v > 0

    for key, n in (("volume_size_mm", 3), ("plane_size_mm", 2)):
        if not (isinstance(t[key], list) and len(t[key]) == n and all(map(positive, t[key]))):
            raise err(f"[acceptance] {key}", f"must be {n} positive lengths (mm)")
    if not (isinstance(t["volume_centre_mm"], list) and len(t["volume_centre_mm"]) == 3):
        raise err("[acceptance] volume_centre_mm", "must be x, y, z in the scanner frame (mm)")
    for key in ACCEPTANCE_NUMBERS:
        if not positive(t[key]):
            raise err(f"[acceptance] {key}", f"must be a positive length (mm), got {t[key]!r}")
    part3 = set(t) & (ACCEPTANCE_PART3 - {"mpe3_mm"})
    if part3 and part3 != ACCEPTANCE_PART3 - {"mpe3_mm"}:
        raise err("[acceptance]", f"a Part 3 test needs all of "
                                  f"{', '.join(sorted(ACCEPTANCE_PART3 - {'mpe3_mm'}))}")
    for key in part3 - {"part3_positions_world"}:
        if not positive(t[key]):
            raise err(f"[acceptance] {key}", f"must be a positive length (mm), got {t[key]!r}")
    for pos in t.get("part3_positions_world", []):
        if not (isinstance(pos, list) and len(pos) == 6 and any(pos[3:])):
            raise err("[acceptance] part3_positions_world", "each must be x, y, z (mm) and a "
                                                            "direction dx, dy, dz")
    if "decision_rule" in t and t["decision_rule"] not in DECISION_RULES:
        raise err("[acceptance] decision_rule", f"must be iso14253-1 or simple, got "
                                                f"{t['decision_rule']!r}")
    width = t.get("mpe_camera_width_px")
    if width is not None and not (isinstance(width, int) and not isinstance(width, bool)
                                  and width > 0):
        raise err("[acceptance] mpe_camera_width_px", f"must be a positive whole number of "
                                                      f"pixels, got {width!r}")
    for table, known in (("positions", {"sphere", "ballbar", "plane"}),
                         ("mpe_mm", {"PF", "PS", "SD", "F"}), ("mpe3_mm", {"SD"}),
                         ("test_u_mm", {"PF", "PS", "SD", "F", "SD3"})):
        sub = t.get(table, {})
        if not isinstance(sub, dict) or set(sub) - known or not all(map(positive, sub.values())):
            raise err(f"[acceptance] {table}", f"must map {', '.join(sorted(known))} to "
                                               f"positive numbers")
    return dict(t)


def _inspection(t: dict[str, Any], path: Path | None, err) -> dict[str, Any]:
    unknown = set(t) - INSPECTION_KEYS.keys()
    if unknown:
        raise err("[inspection]", f"unknown key {sorted(unknown)[0]!r} (known: "
                                  f"{', '.join(sorted(INSPECTION_KEYS))})")
    out = dict(t)
    for key in ("nominal", "tolerances"):
        if key in out:
            if not isinstance(out[key], str) or not out[key]:
                raise err(f"[inspection] {key}", "must be a file path")
            if path is not None and not Path(out[key]).is_absolute():
                out[key] = str(path.parent / out[key])
    if "align" in out and out["align"] not in ("asmeasured", "bestfit"):
        raise err("[inspection] align", f"must be asmeasured or bestfit, got {out['align']!r}")
    if "decision_rule" in out and out["decision_rule"] not in DECISION_RULES:
        raise err("[inspection] decision_rule",
                  f"must be iso14253-1 or simple, got {out['decision_rule']!r}")
    sigma = out.get("point_sigma_mm")
    if sigma is not None and not (isinstance(sigma, int | float) and sigma >= 0):
        raise err("[inspection] point_sigma_mm", f"must be a number >= 0 (mm), got {sigma!r}")
    T = out.get("T_world_from_part")
    if T is not None:
        import numpy as np

        try:
            m = np.asarray(T, float).reshape(4, 4)
        except (ValueError, TypeError):
            raise err("[inspection] T_world_from_part", "must be a 4x4 matrix (mm)") from None
        if not np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-6):
            raise err("[inspection] T_world_from_part", "is not a rigid transform")
    return out


def _table(raw: dict[str, Any], name: str, err) -> dict[str, Any]:
    value = raw.get(name, {})
    if not isinstance(value, dict):
        raise err(f"[{name}]", "must be a table")
    return value


def _check_driver(driver: str, options: dict[str, Any], key: str, err) -> None:
    from scancell.devices.registry import UnknownDriver, load_driver

    try:
        cls = load_driver(driver)
    except UnknownDriver as exc:
        raise err(f"{key} driver", str(exc)) from None
    validator = jsonschema.Draft202012Validator(cls.OPTIONS_SCHEMA)
    errors = sorted(validator.iter_errors(options), key=lambda e: list(e.path))
    if errors:
        e = errors[0]
        sub = ".".join(str(p) for p in e.path) or "(table)"
        raise err(f"{key} {sub}", f"{e.message} (driver {driver})")
