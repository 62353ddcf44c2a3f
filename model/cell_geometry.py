"""What the planner and the scan job need to know of a cell: robot base, scanner mount, SMR,
tracker position, rail (mm, frames as in docs/explanation/frames-and-units.md). A cell config
states it in ``[planner]``; the simulated cell supplies its own."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from scancell.model.config_keys import REQUIRED, KeySpec
from scancell.model.rail_path import RailPath
from scancell.model.robot_model import RobotModel
from scancell.protocols.plan import DEFAULT_J6_ANGLES_DEG

#: the scanner's rear SMR (the paper's, the ECS and hand-eye one) in a cluster's names
REAR_SMR = "rear"


def _unit(v: Any) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


class GeometryError(ValueError):
    """A ``[planner]`` table is missing a key or has a malformed value."""


#: the default clearance (mm) between the scanner's optical centres and any cell object: the
#: simulated scanner's housing reaches 60 mm around its cameras and projector, and 40 mm more
#: covers the arm's path deviation between taught poses at speed
DEFAULT_CLEARANCE_MM = 100.0


#: how far the planner tilts a view from a patch's normal (deg, four ways each): 20 deg, and 45 so
#: that a groove or a flange's foot is in sight of both cameras from some view (the car rear's
#: plan reached 1.7 % less of the part without it once a view had to be seen by each camera),
#: and a roof or a lid leans towards a tracker
DEFAULT_VIEW_TILTS_DEG = (20.0, 45.0)


#: ``[planner]``: what the planner and the scan job know of a real cell (world = the tracker's
#: frame, mm); the simulated cell supplies its own
PLANNER_KEYS: dict[str, KeySpec] = {
    "T_world_from_base": KeySpec("4x4 matrix", "the robot base in the tracker frame", REQUIRED,
                                 "mm"),
    "T_flange_from_mcs": KeySpec("4x4 matrix", "the scanner (MCS, the left camera) on the "
                                               "flange: the nominal hand-eye", REQUIRED, "mm"),
    "rig_mid_in_flange_mm": KeySpec("3 numbers", "the midpoint between the cameras in the flange "
                                                 "frame", REQUIRED, "mm"),
    "smr_in_mcs_mm": KeySpec("3 numbers", "the scanner's rear SMR in MCS", REQUIRED, "mm"),
    "smr_opening_in_mcs": KeySpec("3 numbers", "the direction the rear SMR's opening faces (MCS)",
                                  [0, 0, -1]),
    "tracker_world_mm": KeySpec("3 numbers", "the tracker's head (home set-up)", REQUIRED, "mm"),
    "tracker_stations_mm": KeySpec("table name = [x, y, z]", "where a moved tracker's head may "
                                   "stand (its tripod's marks, world); absent: a ring round the "
                                   "part at home's distance and heights", {}, "mm"),
    "floor_z_mm": KeySpec("number", "the floor (world z): the scanner keeps clearance_mm above it",
                          None, "mm"),
    "view_tilts_deg": KeySpec("list of numbers", "how far the planner tilts a view from a "
                                                 "patch's normal (four ways each)",
                                 list(DEFAULT_VIEW_TILTS_DEG), "°"),
    "smr_acceptance_deg": KeySpec("number", "the SMR's acceptance half-angle", 30.0, "°"),
    "standoff_mm": KeySpec("number", "the scanner's working distance", 650.0, "mm"),
    "field_mm": KeySpec("2 numbers", "the usable field at the standoff (x, y)", [380.0, 280.0],
                        "mm"),
    "depth_mm": KeySpec("2 numbers", "the usable depth around the standoff", [-90.0, 90.0], "mm"),
    "rail_axis": KeySpec("3 numbers", "the external linear axis carrying the robot (unit vector, "
                                      "world); absent: no rail"),
    "rail_path": KeySpec("list of {length_mm, turn_deg}", "a track of straight and curved "
                         "modules from the base's position along rail_axis (+ turns left); "
                         "absent: a straight rail", [], "mm, °"),
    "rail_positions_mm": KeySpec("list of numbers", "the rail positions the planner may use", [],
                                 "mm"),
    "rail_speed_mm_s": KeySpec("number", "the rail's speed between stations", 250.0, "mm/s"),
    "smr_cluster": KeySpec("table name = {mcs_mm, opening}",
                           "SMR nests on the scanner besides the rear one, as drawn (MCS)", {}),
    "obstacles": KeySpec("list of {name, sphere = {centre, radius}} or {name, capsule = {a, b, "
                         "radius}}", "cell objects the scanner keeps clear of (world)", [], "mm"),
    "clearance_mm": KeySpec("number", "how far the scanner's optical centres keep from an "
                                      "obstacle", DEFAULT_CLEARANCE_MM, "mm"),
    "projector_in_mcs_mm": KeySpec("3 numbers", "the projector's optical centre in MCS (its "
                                   "calibration): the planner keeps it clear of the part and "
                                   "needs it in sight of what a view measures; absent: the "
                                   "rig's midpoint", None, "mm"),
    "park_joints_deg": KeySpec("6 numbers", "the arm folded clear of the part: a move between "
                               "stations that would sweep the scanner too near the part goes "
                               "through it when backing off along the views is not enough; "
                               "absent: back off only", None, "°"),
}


@dataclass(frozen=True)
class Obstacle:
    """A cell object the scanner must keep clear of: a capsule from ``a`` to ``b`` of
    ``radius`` (world mm; a sphere when ``a`` equals ``b``): a ball bar, a nest and its stand,
    a fixture's post."""

    name: str
    a: np.ndarray
    b: np.ndarray
    radius: float

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (mm) of world points from the object's surface (negative inside)."""
        p = np.atleast_2d(np.asarray(points, float))
        ab = self.b - self.a
        L2 = float(ab @ ab)
        t = np.clip(((p - self.a) @ ab) / L2, 0.0, 1.0) if L2 > 0 else np.zeros(len(p))
        return np.linalg.norm(p - (self.a + t[:, None] * ab), axis=1) - self.radius

    @classmethod
    def from_table(cls, t: dict[str, Any], where: str) -> Obstacle:
        name = str(t.get("name") or where)
        if "sphere" in t:
            c = np.asarray(t["sphere"]["centre"], float).reshape(3)
            return cls(name, c, c, float(t["sphere"]["radius"]))
        if "capsule" in t:
            c = t["capsule"]
            return cls(name, np.asarray(c["a"], float).reshape(3),
                       np.asarray(c["b"], float).reshape(3), float(c["radius"]))
        raise GeometryError(f"{where}: give a sphere = {{centre, radius}} or a capsule = "
                            f"{{a, b, radius}} (world mm)")


@dataclass(frozen=True)
class CellGeometry:
    """What the planner needs to know of the cell (mm, frames as in docs/explanation/frames-and-units.md)."""

    T_world_from_base: np.ndarray
    T_flange_from_mcs: np.ndarray
    #: Midpoint between the cameras in the flange frame; the flange z axis is the scanner's
    #: viewing direction (the bisector) and x its baseline.
    rig_mid_in_flange: np.ndarray
    smr_in_mcs_mm: np.ndarray
    smr_opening_in_mcs: np.ndarray
    tracker_world_mm: np.ndarray
    smr_acceptance_deg: float = 30.0
    standoff_mm: float = 650.0
    field_mm: tuple[float, float] = (380.0, 280.0)  # usable field at the standoff (x, y)
    depth_mm: tuple[float, float] = (-90.0, 90.0)  # around the standoff
    max_incidence_deg: float = 65.0
    j6_angles_deg: tuple[float, float] = DEFAULT_J6_ANGLES_DEG
    #: An external linear axis carrying the robot (unit vector in world) and the positions (mm)
    #: the planner may use; empty: no axis.
    rail_axis: tuple[float, float, float] | None = None
    rail_positions_mm: tuple[float, ...] = ()
    #: the axis's track when it is not straight (curved modules turn the base with it)
    rail_path: RailPath | None = None
    #: how fast the rail moves between stations (mm/s): what a move along it costs
    rail_speed_mm_s: float = 250.0
    robot: RobotModel = field(default_factory=RobotModel)
    #: SMR nests on the scanner besides its rear SMR, as drawn (CAD): name -> (centre in mcs,
    #: opening direction in mcs). Where the job points the tracker; the hand-eye job measures
    #: their true positions (the cluster calibration).
    smr_cluster: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    #: cell objects the scanner keeps ``clearance_mm`` from (the part: its standoff)
    obstacles: tuple[Obstacle, ...] = ()
    clearance_mm: float = DEFAULT_CLEARANCE_MM
    #: where a moved tracker may stand (world, mm); empty: a ring round the part
    tracker_stations_mm: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    #: the floor's height (world z, mm), None: not stated
    floor_z_mm: float | None = None
    #: the planner's view tilts from a patch's normal (deg)
    view_tilts_deg: tuple[float, ...] = DEFAULT_VIEW_TILTS_DEG
    #: the arm folded clear of the part (deg): a move's last way round (None: not stated)
    park_joints_deg: tuple[float, ...] | None = None
    #: the projector's optical centre in MCS (mm), None: at the rig's midpoint
    projector_in_mcs_mm: tuple[float, float, float] | None = None

    def optical_centres_in_flange(self) -> np.ndarray:
        """(3, 3) the left camera (MCS origin), the projector (``projector_in_mcs_mm``, or the
        rig midpoint when not stated) and the right camera (mirrored about the midpoint), in
        the flange frame (mm)."""
        T = np.asarray(self.T_flange_from_mcs, float)
        left = T[:3, 3]
        mid = np.asarray(self.rig_mid_in_flange, float)
        projector = (mid if self.projector_in_mcs_mm is None
                     else T[:3, :3] @ np.asarray(self.projector_in_mcs_mm, float) + left)
        return np.stack([left, projector, 2 * mid - left])

    def optical_centres(self, T_world_from_flange: np.ndarray) -> np.ndarray:
        """(3, 3) :meth:`optical_centres_in_flange` with the flange at ``T_world_from_flange``
        (world, mm)."""
        T = np.asarray(T_world_from_flange, float)
        return self.optical_centres_in_flange() @ T[:3, :3].T + T[:3, 3]

    def below_floor(self, T_world_from_flange: np.ndarray) -> bool:
        """The scanner's optical centres at this flange pose come nearer the floor than
        ``clearance_mm`` (never, when the floor is not stated)."""
        return self.floor_clearance(T_world_from_flange) < self.clearance_mm

    def floor_clearance(self, T_world_from_flange: np.ndarray) -> float:
        """How far (mm) the scanner's lowest optical centre stands above the floor (inf when
        the floor is not stated)."""
        if self.floor_z_mm is None:
            return float("inf")
        return float(self.optical_centres(T_world_from_flange)[:, 2].min() - self.floor_z_mm)

    def clearance_problem(self, T_world_from_flange: np.ndarray) -> str | None:
        """Why the scanner at this flange pose is too near a cell object or the floor, or
        None."""
        if self.below_floor(T_world_from_flange):
            return (f"the scanner passes {self.floor_clearance(T_world_from_flange):.0f} mm "
                    f"above the floor (clearance {self.clearance_mm:g} mm)")
        if not self.obstacles:
            return None
        pts = self.optical_centres(T_world_from_flange)
        worst = min((float(o.distance(pts).min()), o.name) for o in self.obstacles)
        if worst[0] >= self.clearance_mm:
            return None
        return (f"the scanner passes {worst[0]:.0f} mm from {worst[1]} (clearance "
                f"{self.clearance_mm:g} mm)")

    def cluster_nominal(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Every SMR on the scanner as drawn: the rear SMR (``rear``, the paper's) and the
        cluster's; name -> (centre in mcs mm, unit opening in mcs)."""
        out = {REAR_SMR: (np.asarray(self.smr_in_mcs_mm, float),
                          _unit(self.smr_opening_in_mcs))}
        out.update({n: (np.asarray(c, float), _unit(o)) for n, (c, o) in self.smr_cluster.items()})
        return out

    def T_world_from_mcs(self, q_rad: np.ndarray, rail_mm: float | None) -> np.ndarray:
        """The scanner's pose by the robot model (nominal, mm): where to point the tracker."""
        return self.base_at(rail_mm) @ self.robot.fk(np.asarray(q_rad, float)) \
            @ self.T_flange_from_mcs

    def smr_positions(self, q_rad: np.ndarray, rail_mm: float | None,
                      T_world_from_tracker: np.ndarray | None = None
                      ) -> dict[str, tuple[np.ndarray, float]]:
        """Every SMR on the scanner at this pose by the robot model: name -> (centre in the
        tracker's frame, mm; angle between its opening and the beam, deg). The tracker head
        sits at ``tracker_world_mm`` of its frame, which is ``world`` unless the nests
        re-located it (``T_world_from_tracker``)."""
        return self.smr_positions_at(self.T_world_from_mcs(q_rad, rail_mm), T_world_from_tracker)

    def smr_positions_at(self, T_world_from_mcs: np.ndarray,
                         T_world_from_tracker: np.ndarray | None = None
                         ) -> dict[str, tuple[np.ndarray, float]]:
        """:meth:`smr_positions` with the scanner at ``T_world_from_mcs`` (mm)."""
        T_wt = np.eye(4) if T_world_from_tracker is None else np.asarray(T_world_from_tracker,
                                                                          float)
        T_tm = np.linalg.inv(T_wt) @ np.asarray(T_world_from_mcs, float)
        head = np.asarray(self.tracker_world_mm, float)
        out = {}
        for name, (c, o) in self.cluster_nominal().items():
            p = T_tm[:3, :3] @ c + T_tm[:3, 3]
            to_tracker = (head - p) / np.linalg.norm(head - p)
            cos = float(np.clip(to_tracker @ (T_tm[:3, :3] @ o), -1.0, 1.0))
            out[name] = (p, float(np.degrees(np.arccos(cos))))
        return out

    def facing_smrs(self, q_rad: np.ndarray, rail_mm: float | None,
                    T_world_from_tracker: np.ndarray | None = None, margin_deg: float = 3.0
                    ) -> dict[str, np.ndarray]:
        """The SMRs of :meth:`smr_positions` whose opening faces the tracker within the
        acceptance less ``margin_deg``: name -> centre in the tracker's frame (mm). Occlusion
        is not predicted: the tracker finds out."""
        return {n: p for n, (p, angle) in
                self.smr_positions(q_rad, rail_mm, T_world_from_tracker).items()
                if angle <= self.smr_acceptance_deg - margin_deg}

    def base_at(self, rail_mm: float | None) -> np.ndarray:
        """The robot base's pose (world, mm) at rail position ``rail_mm`` (None: no rail)."""
        path = self.rail_path or RailPath(tuple(self.rail_axis or (0.0, 1.0, 0.0)))
        return path.base_at(self.T_world_from_base, rail_mm)

    def rail_nearest(self, target: np.ndarray) -> list[float | None]:
        """The rail positions the planner may use, the base nearest ``target`` (world, mm)
        first: the arm works best mid-reach. [None] without a rail."""
        if not self.rail_positions_mm:
            return [None]
        d = np.linalg.norm(self._rail_bases_xy - np.asarray(target, float)[:2], axis=1)
        return [self.rail_positions_mm[i] for i in np.argsort(d, kind="stable")]

    @cached_property
    def _rail_bases_xy(self) -> np.ndarray:
        """(positions, 2) where the base stands at each planner rail position (world, mm)."""
        return np.array([self.base_at(r)[:2, 3] for r in self.rail_positions_mm])

    @classmethod
    def from_table(cls, t: dict[str, Any]) -> CellGeometry:
        """From a cell config's ``[planner]`` table (matrices as nested lists); raises
        GeometryError naming a missing, unknown or malformed key. ``scancell.config`` is its one
        caller for config files."""
        unknown = set(t) - PLANNER_KEYS.keys()
        if unknown:
            raise GeometryError(f"unknown key {sorted(unknown)[0]!r} (known: "
                                f"{', '.join(PLANNER_KEYS)})")
        try:
            g = cls(np.asarray(t["T_world_from_base"], float),
                    np.asarray(t["T_flange_from_mcs"], float),
                    np.asarray(t["rig_mid_in_flange_mm"], float),
                    np.asarray(t["smr_in_mcs_mm"], float),
                    np.asarray(t.get("smr_opening_in_mcs", [0, 0, -1]), float),
                    np.asarray(t["tracker_world_mm"], float),
                    float(t.get("smr_acceptance_deg", 30.0)),
                    float(t.get("standoff_mm", 650.0)),
                    tuple(t.get("field_mm", (380.0, 280.0))),
                    tuple(t.get("depth_mm", (-90.0, 90.0))),
                    rail_axis=tuple(t["rail_axis"]) if t.get("rail_axis") else None,
                    rail_positions_mm=tuple(float(v) for v in t.get("rail_positions_mm", ())),
                    rail_path=(RailPath.from_table(t.get("rail_axis"), t["rail_path"])
                               if t.get("rail_path") else None),
                    rail_speed_mm_s=float(t.get("rail_speed_mm_s", 250.0)),
                    smr_cluster=_cluster(t.get("smr_cluster", {})),
                    obstacles=tuple(Obstacle.from_table(o, f"obstacles[{i}]")
                                    for i, o in enumerate(t.get("obstacles", []))),
                    clearance_mm=float(t.get("clearance_mm", DEFAULT_CLEARANCE_MM)),
                    tracker_stations_mm={str(k): tuple(float(x) for x in np.reshape(v, 3))
                                         for k, v in (t.get("tracker_stations_mm") or {}).items()},
                    floor_z_mm=(float(t["floor_z_mm"]) if t.get("floor_z_mm") is not None
                                else None),
                    view_tilts_deg=tuple(float(v) for v in t.get("view_tilts_deg",
                                                                       DEFAULT_VIEW_TILTS_DEG)),
                    park_joints_deg=(tuple(float(v) for v in t["park_joints_deg"])
                                     if t.get("park_joints_deg") is not None else None),
                    projector_in_mcs_mm=(tuple(float(v) for v in np.reshape(
                        t["projector_in_mcs_mm"], 3)) if t.get("projector_in_mcs_mm")
                        is not None else None))
        except (TypeError, ValueError) as exc:
            raise GeometryError(str(exc)) from None
        except KeyError as exc:
            raise GeometryError(f"missing key {exc}") from None
        if not g.clearance_mm >= 0:
            raise GeometryError(f"clearance_mm must be >= 0 mm, got {g.clearance_mm}")
        if not g.rail_speed_mm_s > 0:
            raise GeometryError(f"rail_speed_mm_s must be > 0 mm/s, got {g.rail_speed_mm_s}")
        if g.park_joints_deg is not None and (
                len(g.park_joints_deg) != 6
                or not g.robot.within_limits(np.radians(g.park_joints_deg))):
            raise GeometryError(f"park_joints_deg must be 6 joint angles (deg) inside the "
                                f"robot's limits, got {list(g.park_joints_deg)}")
        return g


def _cluster(t: Any) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``smr_cluster = {name = {mcs_mm = [x, y, z], opening = [x, y, z]}, ...}``."""
    if not isinstance(t, dict):
        raise GeometryError("smr_cluster must be a table of SMRs: name = {mcs_mm, opening}")
    out = {}
    for name, v in t.items():
        if name == REAR_SMR:
            raise GeometryError(f"smr_cluster: {REAR_SMR!r} is the rear SMR (smr_in_mcs_mm); "
                                f"give the cluster's others")
        try:
            c, o = np.asarray(v["mcs_mm"], float), np.asarray(v["opening"], float)
        except (KeyError, TypeError, ValueError) as exc:
            raise GeometryError(f"smr_cluster.{name}: needs mcs_mm and opening, 3 numbers "
                                f"each ({exc})") from None
        if c.shape != (3,) or o.shape != (3,) or not np.linalg.norm(o) > 0:
            raise GeometryError(f"smr_cluster.{name}: mcs_mm and opening must be 3 numbers, "
                                f"the opening not zero")
        out[str(name)] = (c, o / np.linalg.norm(o))
    return out
