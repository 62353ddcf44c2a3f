"""A measurement plan: the stations of a ``scan_part`` job. Pure: parsing and formatting, no I/O.

TOML (or the same structure as JSON)::

    [plan]
    name = "car_rear"
    speed = 0.2                  # fraction of the robot's maximum joint speed
    j6_angles_deg = [120.0, -120.0] # the J6 turns for P2, P3 (those of the hand-eye calibration)
    tracker_repeats = 5          # tracker shots averaged per point
    ecs = "j6"                   # the scanner's pose: "j6" (the paper's J6 turns of the rear
                                 # SMR) or "cluster" (the SMR cluster, no robot motion; J6
                                 # turns where fewer than 3 SMRs face the tracker)
    nominal = "/data/cad/car_rear.step"  # optional: the part's CAD, for the inspect worker
    park_joints_deg = [0.0, 0.0, 0.0, 0.0, -90.0, 0.0]  # optional: the arm folded clear of
                                 # the part; a scanner check between stations goes there first

    [[station]]
    name = "s01"
    joints_deg = [0.0, 10.0, -5.0, 0.0, -60.0, 0.0]
    axis_mm = 0.0                # optional: external axis position
    ecs = "j6"                   # optional: this station's ECS method (default the plan's)
    tracker = "t1"               # optional: the tracker station it is measured from (default
                                 # "home": where the tracker stands when the job starts)
    via = [{joints_deg = [...], axis_mm = 0.0}]  # optional: the poses the move from the
                                 # station before passes through, in order (``scancell plan``
                                 # routes a move that would sweep the scanner through the part)
    park_via = [{joints_deg = [...]}]  # optional: the poses from the station to the park pose
                                 # (at its rail), in order; the way back is the reverse
    park_clear = false           # optional: that way does not keep the clearance (default true)

    [tracker.t1]                 # a tracker station the job moves the tracker to (roughly:
    position_mm = [2500.0, -3000.0, 0.0]   # the reference nests locate it), world, mm
    yaw_deg = 40.0               # its turn about world z (deg)

Stations are in joint space (degrees; ``scancell plan`` writes them from the robot model), or
as the scanner's pose in the tracker frame, solved by inverse kinematics on the daemon's robot
model when the job starts (the cell config's ``[planner]`` table gives the robot base and the
scanner mount)::

    [[station]]
    name = "s02"
    mcs_pose_world = [3000.0, 120.0, 1150.0, 0.0, 90.0, 0.0]   # x, y, z mm; rx, ry, rz deg
                                                               # (extrinsic xyz, scipy)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from scancell.protocols.keys import check_name

#: J6 turns (deg) for P2 and P3: a third of a turn each way puts P1..P3 on an equilateral
#: triangle, the best-conditioned ECS from three points (measured on the simulated cell: the
#: ECS-only error of a frontal scan 0.010 mm mean, against 0.11 mm with turns of 30 and 60 deg).
#: The SMR's opening must face along J6 for the tracker to keep it over such turns.
DEFAULT_J6_ANGLES_DEG: tuple[float, float] = (120.0, -120.0)

#: how a station's scanner pose is measured: the paper's J6 turns, or the SMR cluster
ECS_METHODS = ("j6", "cluster")


#: the tracker station where the tracker stands when a job starts: the cell's ``world``
HOME_TRACKER = "home"


class PlanError(ValueError):
    """A plan that cannot be run; the message names the station and the key."""


@dataclass(frozen=True)
class Via:
    """A pose the arm passes through on its way to a station: joints (deg) and the rail (mm,
    None: where it is)."""

    joints_deg: tuple[float, ...]
    axis_mm: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {"joints_deg": list(self.joints_deg),
                **({} if self.axis_mm is None else {"axis_mm": self.axis_mm})}


@dataclass(frozen=True)
class PlanStation:
    name: str
    joints_deg: tuple[float, ...] | None
    axis_mm: float | None = None
    #: x, y, z (mm), rx, ry, rz (deg, extrinsic xyz): MCS in world, when not in joint space.
    mcs_pose_world: tuple[float, ...] | None = None
    #: The J6 turn direction the planner found the tracker sees (the job tries it first).
    j6_sign: int = 1
    #: this station's ECS method (None: the plan's)
    ecs: str | None = None
    #: the tracker station it is measured from (HOME_TRACKER: where the tracker stands at the
    #: job's start)
    tracker: str = HOME_TRACKER
    #: the poses the move from the station before passes through, in order
    via: tuple[Via, ...] = ()
    #: the poses from the station to the plan's park pose at its rail, in order (and back,
    #: reversed)
    park_via: tuple[Via, ...] = ()
    #: whether that way keeps the clearance (a scanner check due at a station that cannot
    #: reach the park pose clear waits for the next one)
    park_clear: bool = True

    def poses(self) -> list[tuple[str, Via]]:
        """Every pose the job may command for this station, named as an error names it: the
        station (""), its way in (" via[k]") and its way to the park pose (" park_via[k]")."""
        return [("", Via(self.joints_deg, self.axis_mm)),
                *((f" via[{k}]", v) for k, v in enumerate(self.via)),
                *((f" park_via[{k}]", v) for k, v in enumerate(self.park_via))]


@dataclass(frozen=True)
class TrackerStation:
    """Where a plan has the tracker moved to, roughly (the reference nests locate it)."""

    name: str
    position_mm: tuple[float, float, float]  # world, mm
    yaw_deg: float = 0.0  # about world z

    def T_world_from_base(self) -> Any:
        """The rough pose of its base (head at the translation) as a 4x4 (numpy)."""
        import numpy as np

        c, s_ = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        T = np.eye(4)
        T[:2, :2] = [[c, -s_], [s_, c]]
        T[:3, 3] = self.position_mm
        return T


@dataclass(frozen=True)
class Plan:
    name: str
    stations: tuple[PlanStation, ...]
    speed: float = 0.2
    j6_angles_deg: tuple[float, float] = DEFAULT_J6_ANGLES_DEG
    tracker_repeats: int = 5
    extra: dict[str, Any] = field(default_factory=dict)  # planner's report: coverage, overlaps
    #: the part's nominal CAD (a path the inspect worker can read), or None
    nominal: str | None = None
    #: the ECS method of stations that do not name one (ECS_METHODS)
    ecs: str = "j6"
    #: the tracker stations the stations name, besides HOME_TRACKER
    trackers: dict[str, TrackerStation] = field(default_factory=dict)
    #: the arm folded clear of the part (deg), where a scanner check between stations starts
    #: and ends (each station's ``park_via`` leads there); None: the plan does not say
    park_joints_deg: tuple[float, ...] | None = None

    def subset(self, names: set[str] | list[str]) -> Plan:
        """The stations named, in the plan's order. A station whose planned predecessor is left
        out is reached through the park pose (its predecessor's ``park_via`` out, the rail
        with the arm parked, its own back) when the plan has one; otherwise by its ``via`` as
        planned."""
        keep = [s for s in self.stations if s.name in names]
        if self.park_joints_deg is None:
            return replace(self, stations=tuple(keep))
        before = {s.name: p for p, s in zip(self.stations, self.stations[1:], strict=False)}
        out = []
        for prev, s in zip([None, *keep], keep, strict=False):
            if prev is not None and before.get(s.name) is not prev:
                s = replace(s, via=self.park_between(prev, s))
            out.append(s)
        return replace(self, stations=tuple(out))

    def to_park(self, a: PlanStation, axis_mm: float | None) -> tuple[Via, ...]:
        """The way from station ``a`` to the park pose at rail ``axis_mm``: ``a``'s
        ``park_via``, the park pose at ``a``'s rail, then at ``axis_mm``. Needs
        :attr:`park_joints_deg`."""
        assert self.park_joints_deg is not None
        park = self.park_joints_deg
        return (*a.park_via, Via(park, a.axis_mm), Via(park, axis_mm))

    def park_between(self, a: PlanStation | None, b: PlanStation,
                     axis_mm: float | None = None) -> tuple[Via, ...]:
        """The way from station ``a`` (None: the park pose at rail ``axis_mm``) to station
        ``b`` through the park pose: :meth:`to_park` at ``b``'s rail, then ``b``'s
        ``park_via`` reversed."""
        assert self.park_joints_deg is not None
        park = self.park_joints_deg
        head = ((Via(park, axis_mm), Via(park, b.axis_mm)) if a is None
                else self.to_park(a, b.axis_mm))
        return (*head, *reversed(b.park_via))

    def to_json(self) -> dict[str, Any]:
        head: dict[str, Any] = {"name": self.name, "speed": self.speed,
                                "j6_angles_deg": list(self.j6_angles_deg),
                                "tracker_repeats": self.tracker_repeats}
        if self.nominal:
            head["nominal"] = self.nominal
        if self.ecs != "j6":
            head["ecs"] = self.ecs
        if self.park_joints_deg is not None:
            head["park_joints_deg"] = list(self.park_joints_deg)
        if self.extra:
            head["report"] = self.extra
        stations = []
        for s in self.stations:
            d: dict[str, Any] = {"name": s.name}
            if s.joints_deg is not None:
                d["joints_deg"] = list(s.joints_deg)
            if s.mcs_pose_world is not None:
                d["mcs_pose_world"] = list(s.mcs_pose_world)
            if s.j6_sign != 1:
                d["j6_sign"] = s.j6_sign
            if s.ecs is not None:
                d["ecs"] = s.ecs
            if s.axis_mm is not None:
                d["axis_mm"] = s.axis_mm
            if s.tracker != HOME_TRACKER:
                d["tracker"] = s.tracker
            if s.via:
                d["via"] = [v.to_json() for v in s.via]
            if s.park_via:
                d["park_via"] = [v.to_json() for v in s.park_via]
            if not s.park_clear:
                d["park_clear"] = False
            stations.append(d)
        out: dict[str, Any] = {"plan": head, "station": stations}
        if self.trackers:
            out["tracker"] = {t.name: {"position_mm": list(t.position_mm), "yaw_deg": t.yaw_deg}
                              for t in self.trackers.values()}
        return out

    def to_toml(self) -> str:
        d = self.to_json()
        lines = ["[plan]"]
        lines += [f"{k} = {_toml(v)}" for k, v in d["plan"].items() if k != "report"]
        for k, v in d["plan"].get("report", {}).items():
            lines.append(f"# {k}: {v}")
        for s in d["station"]:
            lines += ["", "[[station]]"] + [f"{k} = {_toml(v)}" for k, v in s.items()]
        for name, t in d.get("tracker", {}).items():
            lines += ["", f"[tracker.{name}]"] + [f"{k} = {_toml(v)}" for k, v in t.items()]
        return "\n".join(lines) + "\n"


def plan_from_text(text: str, name: str) -> dict[str, Any]:
    """The plan structure of a TOML (or, by ``.json`` name, JSON) document, checked."""
    import json
    import tomllib

    try:
        obj = json.loads(text) if name.endswith(".json") else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise PlanError(f"{name}: not valid {'JSON' if name.endswith('.json') else 'TOML'}: "
                        f"{exc}") from None
    parse_plan(obj, name)
    return obj


def _toml(v: Any) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + "}"
    if isinstance(v, float):
        return repr(round(v, 6))
    return str(v)


def _number(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise PlanError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def parse_plan(obj: Any, where: str = "plan") -> Plan:
    """A plan from its TOML/JSON structure; raises PlanError naming what is wrong and where."""
    if not isinstance(obj, dict):
        raise PlanError(f"{where}: expected a table with [plan] and [[station]]")
    head = obj.get("plan", {})
    if not isinstance(head, dict):
        raise PlanError(f"{where}: [plan] must be a table")
    stations = obj.get("station")
    if not isinstance(stations, list) or not stations:
        raise PlanError(f"{where}: no [[station]] entries")
    speed = _number(head.get("speed", 0.2), f"{where}: [plan] speed")
    if not 0 < speed <= 1:
        raise PlanError(f"{where}: [plan] speed must be in (0, 1], got {speed}")
    angles = head.get("j6_angles_deg", list(DEFAULT_J6_ANGLES_DEG))
    if not isinstance(angles, list) or len(angles) != 2:
        raise PlanError(f"{where}: [plan] j6_angles_deg must be two angles (P2, P3)")
    a = tuple(_number(x, f"{where}: [plan] j6_angles_deg") for x in angles)
    if abs(a[0]) < 5 or abs(a[1] - a[0]) < 5 or abs(a[1]) < 5:
        raise PlanError(f"{where}: [plan] j6_angles_deg {list(a)}: the turns must differ from 0 "
                        f"and from each other by at least 5 deg, or the ECS is degenerate")
    repeats = head.get("tracker_repeats", 5)
    if isinstance(repeats, bool) or not isinstance(repeats, int) or not 1 <= repeats <= 100:
        raise PlanError(f"{where}: [plan] tracker_repeats must be an integer 1..100")
    nominal = head.get("nominal")
    if nominal is not None and (not isinstance(nominal, str) or not nominal.strip()):
        raise PlanError(f"{where}: [plan] nominal must be the path of the part's CAD (STEP or "
                        f"mesh), got {nominal!r}")
    ecs = _ecs_method(head.get("ecs", "j6"), f"{where}: [plan] ecs")
    trackers = _tracker_stations(obj.get("tracker", {}), where)
    out: list[PlanStation] = []
    seen: set[str] = set()
    for i, s in enumerate(stations):
        at = f"{where}: station {i + 1}"
        if not isinstance(s, dict):
            raise PlanError(f"{at}: must be a table")
        name = s.get("name", f"s{i + 1:02d}")
        try:
            check_name("station", name)
        except ValueError as exc:
            raise PlanError(f"{at}: {exc}") from None
        if name in seen:
            raise PlanError(f"{at}: duplicate station name {name!r}")
        seen.add(name)
        q, pose = s.get("joints_deg"), s.get("mcs_pose_world")
        if (q is None) == (pose is None):
            raise PlanError(f"{at} ({name}): give joints_deg (6 angles, deg) or mcs_pose_world "
                            f"(x, y, z mm, rx, ry, rz deg), one of them")
        joints = pose6 = None
        if q is not None:
            if not isinstance(q, list) or len(q) != 6:
                raise PlanError(f"{at} ({name}): joints_deg must be 6 angles in degrees")
            joints = tuple(_number(x, f"{at} ({name}) joints_deg") for x in q)
        else:
            if not isinstance(pose, list) or len(pose) != 6:
                raise PlanError(f"{at} ({name}): mcs_pose_world must be x, y, z (mm), rx, ry, "
                                f"rz (deg)")
            pose6 = tuple(_number(x, f"{at} ({name}) mcs_pose_world") for x in pose)
        axis = s.get("axis_mm")
        sign = s.get("j6_sign", 1)
        if sign not in (1, -1):
            raise PlanError(f"{at} ({name}): j6_sign must be 1 or -1, got {sign!r}")
        station_ecs = (None if s.get("ecs") is None
                       else _ecs_method(s["ecs"], f"{at} ({name}) ecs"))
        tracker = s.get("tracker", HOME_TRACKER)
        if tracker != HOME_TRACKER and tracker not in trackers:
            raise PlanError(f"{at} ({name}): tracker {tracker!r} is not a [tracker.<name>] of "
                            f"the plan ({', '.join([HOME_TRACKER, *trackers])})")
        out.append(PlanStation(name, joints, None if axis is None
                               else _number(axis, f"{at} ({name}) axis_mm"), pose6, sign,
                               station_ecs, str(tracker),
                               _vias(s.get("via", []), f"{at} ({name}) via"),
                               _vias(s.get("park_via", []), f"{at} ({name}) park_via"),
                               _flag(s.get("park_clear", True), f"{at} ({name}) park_clear")))
    park = head.get("park_joints_deg")
    if park is not None and (not isinstance(park, list) or len(park) != 6):
        raise PlanError(f"{where}: [plan] park_joints_deg must be 6 angles in degrees")
    return Plan(str(head.get("name", "plan")), tuple(out), speed, (a[0], a[1]), repeats,
                dict(head.get("report", {})) if isinstance(head.get("report"), dict) else {},
                nominal, ecs, trackers,
                None if park is None else tuple(_number(x, f"{where}: [plan] park_joints_deg")
                                                 for x in park))


def _flag(v: Any, where: str) -> bool:
    if not isinstance(v, bool):
        raise PlanError(f"{where}: must be true or false, got {v!r}")
    return v


def _vias(table: Any, where: str) -> tuple[Via, ...]:
    if not isinstance(table, list):
        raise PlanError(f"{where}: must be a list of {{joints_deg, axis_mm}} tables")
    out = []
    for k, v in enumerate(table):
        at = f"{where}[{k}]"
        if not isinstance(v, dict) or set(v) - {"joints_deg", "axis_mm"}:
            raise PlanError(f"{at}: must be a table of joints_deg (6 angles, deg) and, "
                            f"optionally, axis_mm")
        q = v.get("joints_deg")
        if not isinstance(q, list) or len(q) != 6:
            raise PlanError(f"{at}: joints_deg must be 6 angles in degrees")
        axis = v.get("axis_mm")
        out.append(Via(tuple(_number(x, f"{at} joints_deg") for x in q),
                       None if axis is None else _number(axis, f"{at} axis_mm")))
    return tuple(out)


def _tracker_stations(table: Any, where: str) -> dict[str, TrackerStation]:
    if not isinstance(table, dict):
        raise PlanError(f"{where}: [tracker.<name>] must be tables of tracker stations")
    out = {}
    for name, t in table.items():
        at = f"{where}: [tracker.{name}]"
        if name == HOME_TRACKER:
            raise PlanError(f"{at}: {HOME_TRACKER!r} is where the tracker stands at the job's "
                            f"start; name the other stations otherwise")
        try:
            check_name("tracker station", name)
        except ValueError as exc:
            raise PlanError(f"{at}: {exc}") from None
        if not isinstance(t, dict):
            raise PlanError(f"{at}: must be a table with position_mm and yaw_deg")
        pos = t.get("position_mm")
        if not isinstance(pos, list) or len(pos) != 3:
            raise PlanError(f"{at}: position_mm must be x, y, z (mm, world)")
        xyz = tuple(_number(v, f"{at} position_mm") for v in pos)
        out[name] = TrackerStation(name, (xyz[0], xyz[1], xyz[2]),
                                   _number(t.get("yaw_deg", 0.0), f"{at} yaw_deg"))
    return out


def _ecs_method(v: Any, where: str) -> str:
    if v not in ECS_METHODS:
        raise PlanError(f"{where}: must be one of {', '.join(repr(m) for m in ECS_METHODS)}, "
                        f"got {v!r}")
    return str(v)
