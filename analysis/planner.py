"""Station planning: scanner stations that cover a part, with the paper's 10-40 % overlap between
neighbours, every one reachable and inside the joint limits, and the tracker seeing the SMR at all
three J6 positions.

1. The part's surface (a mesh in the tracker frame ``world``, mm) is sampled with normals.
2. Candidate views: surface patches one step apart (the field minus the wanted overlap), each
   looked at along its normal and tilted 20° four ways; the scanner's bisector meets the patch
   ``standoff_mm`` from the rig.
3. A candidate is kept if inverse kinematics reaches it inside the joint limits, J6 can turn by
   the ECS angles (one way or the other), and at those three J6 positions the SMR faces the
   tracker within its acceptance angle with no part in the beam.
4. What a candidate sees: samples inside the field and depth of view, facing the scanner, not
   hidden by the part (ray cast).
5. Stations are chosen greedily by new coverage until ``coverage`` is reached, and ordered by
   the time the moves between them take (the arm at the plan's speed and the rail moving
   together): a nearest-neighbour tour from the first, shortened by 2-opt and or-opt.
   Each move of the tour is swept (``model.move_path``): one that would carry the scanner
   within ``clearance_mm`` of the part, a cell object or the floor on the way is routed
   (:meth:`Planner.route`: stations backed off along their views, the park pose, a pose about
   the joints' midpoint), and a station no way reaches clear is left out; each station's way
   to the park pose is routed the same.
6. With ``tracker_moves`` and the cell's reference nests, views where the tracker at home cannot
   see the scanner's SMR(s) may be measured from another tracker station: candidate stations on
   a ring around the part (at home's distance and height) that see >= 4 nests past the part.
   When the home stations stop adding coverage, the tracker station whose views add the most
   is taken, and so on up to ``tracker_moves``; stations are grouped by tracker station (home
   first: one move per extra station).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any

import numpy as np
import open3d as o3d
from scancell.analysis.smr_cluster import ClusterGeometryError, check_cluster_geometry
from scancell.model.cell_geometry import CellGeometry, GeometryError
from scancell.model.move_path import move_flange_poses
from scancell.model.robot_model import IKError
from scancell.model.transforms import T_rot_z, look_at_flange
from scancell.protocols.plan import ECS_METHODS, HOME_TRACKER, Plan, PlanStation, TrackerStation, Via


class PlanningError(GeometryError):
    """No station can see the part, or the part file is unusable; says which."""


@dataclass
class Candidate:
    name: str
    q: np.ndarray  # rad
    target: np.ndarray
    view: np.ndarray
    sees: np.ndarray  # bool over the surface samples
    j6_sign: float
    rail_mm: float | None = None
    #: the SMRs the tracker sees at the view (``ecs = "cluster"``)
    smrs: tuple[str, ...] = ()
    #: the tracker station it is measured from
    tracker: str = HOME_TRACKER


@dataclass
class PlanReport:
    stations: int
    coverage: float  # share of the reachable surface samples seen by at least one station
    reachable: float  # share of all samples some candidate could see
    #: Per station: its nearest neighbour (most shared surface) and the share of the smaller
    #: view they share.
    neighbours: list[tuple[str, str, float]]
    candidates: int
    candidates_kept: int
    #: Shares of all the part's surface samples the plan leaves unmeasured, by reason (see
    #: :data:`UNMEASURED_REASONS`).
    unmeasured: dict[str, float] = field(default_factory=dict)
    #: the tracker stations the plan uses, home first: name -> head in world (mm)
    tracker_stations: dict[str, list[float]] = field(default_factory=dict)
    #: the coverage (as ``coverage``) after each station, in the order the plan chose them
    #: (most new surface first): how many stations a lower target would take
    coverage_curve: list[float] = field(default_factory=list)
    #: how the moves between stations keep ``clearance_mm`` (:meth:`Planner.route`):
    #: "direct", "backed_off", "parked", "round", or "tight" (none does) -> count; "dropped":
    #: stations left out for no way in that keeps it; "park_<how>": each station's way to the
    #: park pose (where a scanner check between stations goes)
    moves: dict[str, int] = field(default_factory=dict)
    #: the "tight" moves: {"from", "to" (a station or "park"), "via" (poses), "nearest_mm",
    #: "to_what"}, run the way that comes least near
    moves_tight: list[dict[str, Any]] = field(default_factory=list)

    def stations_for(self, share: float) -> int | None:
        """The stations the plan's choice needs to cover ``share`` (as ``coverage``), or None
        if it never does."""
        reached = [i for i, c in enumerate(self.coverage_curve) if c >= share]
        return reached[0] + 1 if reached else None

    def to_json(self) -> dict[str, Any]:
        ov = [o for _, _, o in self.neighbours]
        return {"stations": self.stations, "coverage": round(self.coverage, 4),
                "reachable": round(self.reachable, 4), "candidates": self.candidates,
                "unmeasured": {k: round(v, 4) for k, v in self.unmeasured.items()},
                "candidates_kept": self.candidates_kept,
                "neighbour_overlap_min": round(min(ov), 3) if ov else None,
                "neighbour_overlap_median": round(float(np.median(ov)), 3) if ov else None,
                "neighbour_overlap_max": round(max(ov), 3) if ov else None,
                "stations_with_overlap_10_40": sum(1 for o in ov if 0.10 <= o <= 0.40),
                "tracker_stations": self.tracker_stations,
                "stations_for_coverage": {f"{q:g}": self.stations_for(q)
                                          for q in (0.90, 0.95, 0.97, 0.98, 0.99, 0.995)},
                "coverage_curve": [round(c, 4) for c in self.coverage_curve],
                "moves": self.moves, "moves_tight": self.moves_tight}


#: Why a surface sample is left unmeasured, first reason that applies:
#: ``beam``: views see it, but at none of them does the tracker see the SMR (acceptance cone,
#: or the part in the beam) through the J6 turns; ``reach``: the tracker would see the SMR at a
#: view that sees it, but the robot cannot take that view inside its reach and joint limits
#: (J6 turns included); ``view``: no candidate view sees it (too steep to every view direction
#: tried, or hidden); ``overlap``: a usable view sees it, but the plan stopped at its coverage
#: target or at a view adding too little (``--coverage``).
UNMEASURED_REASONS = ("beam", "reach", "view", "overlap")


def _tilted(v: np.ndarray, *degs: float) -> list[np.ndarray]:
    """``v`` and ``v`` tilted by each of ``degs`` four ways (about the horizontal and about
    the axis across it)."""
    a = np.cross(v, [0.0, 0.0, 1.0])
    a = a / np.linalg.norm(a) if np.linalg.norm(a) > 1e-6 else np.array([0.0, 1.0, 0.0])
    b = np.cross(v, a)
    return [v] + [np.cos(t) * v + np.sin(t) * d for t in np.radians(degs) for d in (a, -a, b, -b)]


#: J6 rolls (deg) a cluster view may take to bring a face of the cluster round to the tracker,
#: the least first
CLUSTER_ROLLS_DEG = (0.0, 30.0, -30.0, 60.0, -60.0, 90.0, -90.0, 120.0, -120.0, 150.0, -150.0,
                     180.0)
#: a view from a tracker station the plan does not use yet scores this share of its new
#: coverage: a move is taken when it adds more than twice what the stations without it would
MOVE_DISCOUNT = 0.5
#: a view is taken only if it adds this much surface not measured yet (mm²; 5 samples at the
#: least): a 30 mm square, under 1 % of the field
MIN_GAIN_MM2 = 900.0

#: How far a routed move backs the scanner off along its view before it turns, as shares of the
#: standoff, tried in order: half the working distance first (the surface the station looks at
#: 1.5 standoffs away, room for the wrist to turn the scanner round), then a whole one (round a
#: sill or a bumper's edge), then a quarter (where the floor or the reach allows no more).
BACK_OFF_SHARES = (0.5, 1.0, 0.25)

#: How many poses a route round the part tries (:meth:`Planner.route`), and their spread about
#: the joints' midpoint (rad): a third of a turn reaches the other side of a sill or a bumper.
ROUND_TRIES = 40
ROUND_SPREAD_RAD = np.radians(40.0)

#: how many stations in a row a plan may leave out for no clear way in (:meth:`Planner.routed`)
MAX_DROPPED_IN_A_ROW = 2

#: a pose on a route: joints (rad) and the rail (mm, None: no rail)
Pose = tuple[np.ndarray, float | None]
#: the job measures the SMRs facing the tracker within the acceptance less this (deg)
FACING_MARGIN_DEG = 3.0
#: how far a moved tracker's tripod, set up by eye on its mark, may land off it (mm): 3 x the
#: 30 mm (1-sigma) a person places a tripod within (the simulated cell's PLACEMENT_SIGMA_MM)
TRACKER_SETUP_MM = 90.0


def _segment_distance(p0: np.ndarray, p1: np.ndarray, a: np.ndarray, b: np.ndarray
                      ) -> np.ndarray:
    """Shortest distance (mm) between segments p0[i]-p1[i] (N, 3) and the segment a-b."""
    d1 = p1 - p0
    d2 = b - a
    r = p0 - a
    aa = np.einsum("ij,ij->i", d1, d1)
    ee = float(d2 @ d2)
    ff = r @ d2
    c = np.einsum("ij,ij->i", d1, r)
    bb = d1 @ d2
    denom = aa * ee - bb * bb
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12, np.clip((bb * ff - c * ee) / denom, 0, 1), 0.0)
        t = (bb * s + ff) / ee if ee > 0 else np.zeros_like(s)
    t = np.clip(t, 0, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(aa > 0, np.clip((bb * t - c) / aa, 0, 1), 0.0)
    return np.linalg.norm(p0 + d1 * s[:, None] - (a + d2 * t[:, None]), axis=1)


class Planner:
    """Stations for a part. ``ecs = "j6"``: the tracker must see the rear SMR at the view and
    at both J6 turns (the paper's); ``"cluster"``: >= 3 SMRs of the scanner, not on a line,
    must face the tracker with no part in the beam, the view rolled about J6 if that brings a
    face round; no J6 turns."""

    def __init__(self, mesh: o3d.geometry.TriangleMesh, geometry: CellGeometry,
                 samples: int = 12000, seed: int = 0, ecs: str = "j6",
                 nests_world: dict[str, np.ndarray] | None = None,
                 tracker_moves: int = 0) -> None:
        if len(mesh.triangles) == 0:
            raise PlanningError("the part mesh has no triangles")
        if ecs not in ECS_METHODS:
            raise PlanningError(f"ecs must be one of {', '.join(ECS_METHODS)}, got {ecs!r}")
        if ecs == "cluster" and not geometry.smr_cluster:
            raise PlanningError("ecs = \"cluster\" needs the scanner's SMR cluster in the cell's "
                                "geometry ([planner] smr_cluster)")
        self.ecs = ecs
        self.g = geometry
        mesh.compute_triangle_normals()
        o3d.utility.random.seed(seed)
        pcd = mesh.sample_points_uniformly(samples, use_triangle_normal=True)
        self.area_per_sample_mm2 = mesh.get_surface_area() / samples
        self.points = np.asarray(pcd.points)
        n = np.asarray(pcd.normals)
        if not _closed_and_outward(mesh):  # a sheet: its normals towards the robot
            base = geometry.T_world_from_base[:3, 3]
            n[np.einsum("ij,ij->i", n, base - self.points) < 0] *= -1
        self.normals = n
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        self.nests = {n: np.asarray(p, float) for n, p in (nests_world or {}).items()}
        #: tracker station -> its head in world (mm); home first
        self.trackers: dict[str, np.ndarray] = {HOME_TRACKER: np.asarray(geometry.tracker_world_mm,
                                                                          float)}
        if tracker_moves > 0 and len(self.nests) >= 4:
            self.trackers.update(self._tracker_candidates())
        self.tracker_moves = tracker_moves

    def _tracker_candidates(self, n: int = 8, min_nests: int = 4) -> dict[str, np.ndarray]:
        """The cell's tracker stations (``tracker_stations_mm``), else stations on a ring
        around the part at home's horizontal distance and height, each at least 1 m from every
        nest and 1.5 m from the robot's base; those seeing ``min_nests`` nests with no part in
        the beam."""
        home = self.trackers[HOME_TRACKER]
        nests = np.array(list(self.nests.values()))
        if self.g.tracker_stations_mm:  # the cell's own marks
            return {n: np.asarray(p, float) for n, p in self.g.tracker_stations_mm.items()
                    if int(self._clear(nests, np.repeat(np.asarray(p, float)[None], len(nests),
                                                        0)).sum()) >= min_nests}
        centre = 0.5 * (self.points.min(axis=0) + self.points.max(axis=0))
        radius = float(np.linalg.norm((home - centre)[:2]))
        a0 = np.arctan2(*(home - centre)[1::-1])
        bases = [self.g.base_at(r)[:3, 3] for r in (list(self.g.rail_positions_mm) or [None])]
        out = {}
        for k in range(1, n):
            a = a0 + 2 * np.pi * k / n
            p = np.array([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a),
                          home[2]])
            if min(np.linalg.norm(p - q) for q in self.nests.values()) < 1000.0:
                continue
            if min(np.linalg.norm((p - b)[:2]) for b in bases) < 1500.0:
                continue
            if int(self._clear(nests, np.repeat(p[None], len(nests), 0)).sum()) < min_nests:
                continue
            out[f"t{len(out) + 1}"] = p
        return out

    # ------------------------------------------------------------------ checks
    def _clear(self, origins: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Which beams from ``origins`` reach ``ends`` past the part and the cell's objects
        (an object a beam starts or ends in, its target's own nest, does not count)."""
        d = ends - origins
        dist = np.linalg.norm(d, axis=1)
        rays = np.hstack([origins, d / dist[:, None]]).astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        clear = hit >= dist - 1.0
        for o in self.g.obstacles:
            own = (o.distance(ends) < 1.0) | (o.distance(origins) < 1.0)
            clear &= own | (_segment_distance(origins, ends, o.a, o.b) > o.radius)
        return clear

    def tracker_sees_smr(self, q: np.ndarray, base: np.ndarray) -> bool:
        """At joints ``q`` on a robot base at ``base``, from home."""
        return self._smr_in_sight(base @ self.g.robot.fk(q), self.trackers[HOME_TRACKER])

    def _smr_in_sight(self, T_world_from_flange: np.ndarray, head: np.ndarray) -> bool:
        """The rear SMR faces the tracker head at ``head`` (world, mm), no part in the beam."""
        g = self.g
        T = T_world_from_flange @ g.T_flange_from_mcs
        smr = T[:3, :3] @ g.smr_in_mcs_mm + T[:3, 3]
        to_tracker = head - smr
        opening = T[:3, :3] @ g.smr_opening_in_mcs
        cos = opening @ to_tracker / np.linalg.norm(to_tracker)
        if cos < np.cos(np.radians(g.smr_acceptance_deg)):
            return False
        return bool(self._clear(smr[None] + 25.0 * to_tracker[None] / np.linalg.norm(to_tracker),
                                head[None])[0])

    def smrs_in_sight(self, T_world_from_flange: np.ndarray,
                      head: np.ndarray | None = None) -> list[str]:
        """The scanner's SMRs (rear and cluster) facing the tracker head at ``head`` (world, mm;
        default home) within the acceptance less FACING_MARGIN_DEG, with no part in the beam.
        A moved tracker stands where a tripod set up by eye lands, up to TRACKER_SETUP_MM off
        its mark: the beam to an SMR r away may turn by atan(TRACKER_SETUP_MM / r) more, so
        its SMRs keep that much more margin (the job, knowing where the tracker landed, measures
        those within FACING_MARGIN_DEG)."""
        g = self.g
        moved = head is not None and not np.allclose(head, self.trackers[HOME_TRACKER])
        head = self.trackers[HOME_TRACKER] if head is None else head
        T_wt = np.eye(4)  # the head at ``head``: readings' frame shifted from home's
        T_wt[:3, 3] = head - np.asarray(g.tracker_world_mm, float)
        pos = g.smr_positions_at(T_world_from_flange @ g.T_flange_from_mcs, T_wt)

        def margin(p: np.ndarray) -> float:
            r = float(np.linalg.norm(head - (p + T_wt[:3, 3])))
            return FACING_MARGIN_DEG + (np.degrees(np.arctan(TRACKER_SETUP_MM / r)) if moved
                                        else 0.0)

        names = [n for n, (p, a) in pos.items() if a <= g.smr_acceptance_deg - margin(p)]
        if not names:
            return []
        pts = np.array([pos[n][0] for n in names]) + T_wt[:3, 3]
        to = head - pts
        to /= np.linalg.norm(to, axis=1)[:, None]
        clear = self._clear(pts + 25.0 * to, np.repeat(head[None], len(pts), 0))
        return [n for n, ok in zip(names, clear, strict=True) if ok]

    def _cluster_roll(self, T_world_from_flange: np.ndarray, head: np.ndarray
                      ) -> tuple[np.ndarray, list[str]] | None:
        """The view rolled about J6 (the least of CLUSTER_ROLLS_DEG) at which >= 3 SMRs not on
        a line are in sight, and those SMRs; None if no roll gives them."""
        nominal = self.g.cluster_nominal()
        for roll in CLUSTER_ROLLS_DEG:
            T = T_world_from_flange @ T_rot_z(roll)
            names = self.smrs_in_sight(T, head)
            if len(names) < 3:
                continue
            try:
                check_cluster_geometry({n: nominal[n][0] for n in names}, "view")
            except ClusterGeometryError:
                continue
            return T, names
        return None

    def _j6_sign(self, T_world_from_flange: np.ndarray, head: np.ndarray) -> float | None:
        """The J6 turn direction with the SMR in sight of the head at ``head`` at all three
        positions (J6 turns the flange about its z axis, so no joint solution is needed)."""
        for sign in (1.0, -1.0):
            if all(self._smr_in_sight(T_world_from_flange @ T_rot_z(sign * a), head)
                   for a in (0.0, *self.g.j6_angles_deg)):
                return sign
        return None

    def reachable(self, T_world_from_flange: np.ndarray, seed: np.ndarray | None,
                  rail_mm: float | None = None, sign: float = 1.0) -> np.ndarray | None:
        """Joints, or None if the robot cannot take the pose inside its reach and limits (with
        ``ecs = "j6"`` the J6 turns in direction ``sign`` too)."""
        g = self.g
        base = g.base_at(rail_mm)
        T_base_from_flange = np.linalg.inv(base) @ T_world_from_flange
        if not g.robot.within_reach(T_base_from_flange):
            return None
        try:
            q = g.robot.ik(T_base_from_flange, seed)
        except IKError:
            return None
        qs = [q] + ([q + np.radians([0, 0, 0, 0, 0, sign * a]) for a in g.j6_angles_deg]
                    if self.ecs == "j6" else [])
        if all(g.robot.within_limits(x) for x in qs):
            return q
        return None

    def seen(self, T_world_from_flange: np.ndarray) -> np.ndarray:
        """Which surface samples the scanner measures at this flange pose: inside the field and
        depth about the rig's bisector, facing the rig's midpoint within ``max_incidence_deg``,
        and in sight of both cameras and the projector, past the part and the cell's
        objects. One camera that sees none of the lit surface decodes nothing."""
        g = self.g
        centres = g.optical_centres(T_world_from_flange)  # left camera, projector, right camera
        R = T_world_from_flange[:3, :3]
        origin = R @ g.rig_mid_in_flange + T_world_from_flange[:3, 3]
        rel = (self.points - origin) @ R  # flange axes: x baseline, z view
        z = rel[:, 2]
        ok = (z > g.standoff_mm + g.depth_mm[0]) & (z < g.standoff_mm + g.depth_mm[1])
        scale = z / g.standoff_mm
        ok &= (np.abs(rel[:, 0]) <= g.field_mm[0] / 2 * scale)
        ok &= (np.abs(rel[:, 1]) <= g.field_mm[1] / 2 * scale)
        to_scanner = origin - self.points
        to_scanner /= np.linalg.norm(to_scanner, axis=1)[:, None]
        ok &= np.einsum("ij,ij->i", self.normals, to_scanner) > np.cos(
            np.radians(g.max_incidence_deg))
        idx = np.flatnonzero(ok)
        for centre in centres:
            if not len(idx):
                break
            towards = centre - self.points[idx]
            towards /= np.linalg.norm(towards, axis=1)[:, None]
            start = self.points[idx] + 0.5 * towards  # just off the surface
            idx = idx[self._clear(start, np.repeat(centre[None], len(idx), axis=0))]
        ok[:] = False
        ok[idx] = True
        return ok

    def part_clearance(self, T_world_from_flange: np.ndarray) -> float:
        """How near (mm) the scanner's nearest optical centre comes to the part at this flange
        pose: the part is an obstacle too, and a view tilted near a concave edge (a wheel
        arch, a door opening) brings one camera within reach of the sheet."""
        centres = self.g.optical_centres(T_world_from_flange).astype(np.float32)
        return float(self.scene.compute_distance(o3d.core.Tensor(centres)).numpy().min())

    def too_near(self, T_world_from_flange: np.ndarray, j6_sign: float | None = None) -> bool:
        """The scanner at this flange pose comes nearer a cell object, the floor or the part
        than the cell's ``clearance_mm``; with ``j6_sign`` (``ecs = "j6"``) at either J6 turn
        too, which swings the cameras about the flange's axis."""
        turns = (0.0,) if j6_sign is None else (0.0, *(j6_sign * a for a in self.g.j6_angles_deg))
        return any(self.g.clearance_problem(T) is not None
                   or self.part_clearance(T) < self.g.clearance_mm
                   for T in (T_world_from_flange @ T_rot_z(a) for a in turns))

    def move_clearance(self, start: Pose, end: Pose, speed: float) -> tuple[float, str]:
        """How near (mm) the scanner's optical centres come along the move from ``start`` to
        ``end`` (the arm at ``speed`` and the rail moving together, ``model.move_path``), and to
        what: "the part", a cell object's name or "the floor". The part's distance is exact
        when it is below ``clearance_mm``, and otherwise only known to be at least that
        (:meth:`_part_nearest_along`)."""
        g = self.g
        Ts = move_flange_poses(g, start[0], start[1], end[0], end[1], speed,
                               max(g.clearance_mm, 1.0) / 2)
        local = g.optical_centres_in_flange()
        tracks = np.einsum("nij,kj->nki", Ts[:, :3, :3], local) + Ts[:, None, :3, 3]
        centres = tracks.reshape(-1, 3)
        near = [(self._part_nearest_along(tracks), "the part")]
        near += [(float(o.distance(centres).min()), o.name) for o in g.obstacles]
        if g.floor_z_mm is not None:
            near.append((float(centres[:, 2].min() - g.floor_z_mm), "the floor"))
        return min(near)

    def _part_nearest_along(self, tracks: np.ndarray) -> float:
        """How near (mm) points along ``k`` tracks of ``n`` points each, ``(n, k, 3)`` in world,
        come to the part: exact when below ``clearance_mm``, else a value at or above it.

        The distance to the part changes no faster than a point moves, so a point ``D`` from
        it vouches for every later one of its track less than ``D - clearance_mm`` further
        along: those are queried no more (sphere tracing). A scanner at its standoff passes
        most samples of a move that way: the part's closest-point query is the planner's
        dearest step (about 50 us a point on the car body's million triangles)."""
        n, k, _ = tracks.shape
        along = np.concatenate([np.zeros((1, k)), np.cumsum(
            np.linalg.norm(np.diff(tracks, axis=0), axis=2), axis=0)])
        at = np.zeros(k, int)
        nearest = np.inf
        while np.any(at < n):
            live = np.flatnonzero(at < n)
            d = self.scene.compute_distance(o3d.core.Tensor(
                tracks[at[live], live].astype(np.float32))).numpy()
            nearest = min(nearest, float(d.min()))
            for j, dj in zip(live, d, strict=True):
                vouched = along[at[j], j] + float(dj) - self.g.clearance_mm
                at[j] = max(at[j] + 1, int(np.searchsorted(along[:, j], vouched, side="left")))
        return nearest

    def backed_off(self, pose: Pose) -> list[Pose]:
        """The station ``pose`` with the scanner backed off along its view by each of
        :data:`BACK_OFF_SHARES` of the standoff that the robot reaches inside its limits with
        the scanner ``clearance_mm`` clear (:meth:`too_near`)."""
        q, rail = pose
        base = self.g.base_at(rail)
        T = base @ self.g.robot.fk(q)
        out = []
        for share in BACK_OFF_SHARES:
            back = T.copy()
            back[:3, 3] -= T[:3, 2] * share * self.g.standoff_mm
            T_base = np.linalg.inv(base) @ back
            if not self.g.robot.within_reach(T_base):
                continue
            try:
                q_back = self.g.robot.ik(T_base, q)
            except IKError:
                continue
            T_back = base @ self.g.robot.fk(q_back)
            if self.g.robot.within_limits(q_back) and not self.too_near(T_back):
                out.append((q_back, rail))
        return out

    def route(self, start: Pose, end: Pose, speed: float
              ) -> tuple[str, list[Pose], tuple[float, str]]:
        """How the move from ``start`` to ``end`` keeps ``clearance_mm``, the poses it passes
        through and how near it comes (mm, to what): "direct" (no poses); "backed_off" (either
        station or both backed off along its view, :data:`BACK_OFF_SHARES`); "parked" (the
        park pose at each station's rail, with or without the back-offs); "round" (a pose
        found at random about the joints' midpoint, :data:`ROUND_TRIES`). When none keeps it:
        "tight", the way that comes least near."""
        direct = self.move_clearance(start, end, speed)
        if direct[0] >= self.g.clearance_mm:
            return "direct", [], direct
        outs, backs = self.backed_off(start), self.backed_off(end)
        pairs = [pair for k in range(len(BACK_OFF_SHARES))
                 for pair in ((_at(outs, k), _at(backs, k)), (_at(outs, k), None),
                              (None, _at(backs, k))) if pair != (None, None)]
        ways = [("backed_off", [p for p in pair if p is not None]) for pair in pairs]
        if self.g.park_joints_deg is not None:
            park = np.radians(self.g.park_joints_deg)
            for pair in [*pairs, (None, None)]:
                parked = [pair[0], (park, start[1]), (park, end[1]), pair[1]]
                ways.append(("parked", [p for p in parked if p is not None]))
        # legs the ways share are swept once; the poses are kept with their result, or a
        # pose made later could take a freed one's id and its answer
        swept: dict[tuple[int, int], tuple[Pose, Pose, tuple[float, str]]] = {}

        def leg(a: Pose, b: Pose) -> tuple[float, str]:
            if (id(a), id(b)) not in swept:
                swept[id(a), id(b)] = (a, b, self.move_clearance(a, b, speed))
            return swept[id(a), id(b)][2]

        best: tuple[str, list[Pose], tuple[float, str]] = ("tight", [], direct)
        for how, via in ways:
            nearest = min(leg(a, b) for a, b in pairwise([start, *via, end]))
            if nearest[0] >= self.g.clearance_mm:
                return how, via, nearest
            if nearest[0] > best[2][0]:
                best = ("tight", via, nearest)
        # a way round: one pose between the widest back-offs, the joints their midpoint
        # shaken at random (seeded: a plan is made again the same)
        out, back = _at(outs, 0), _at(backs, 0)
        a, b = out or start, back or end
        rng = np.random.default_rng(0)
        lo, hi = self.g.robot.limits_rad[:, 0], self.g.robot.limits_rad[:, 1]
        for _ in range(ROUND_TRIES):
            mid = np.clip((a[0] + b[0]) / 2 + rng.normal(0.0, ROUND_SPREAD_RAD, 6), lo, hi)
            way = [p for p in (out, (mid, a[1]), (mid, b[1]), back) if p is not None]
            nearest = min(leg(x, y) for x, y in pairwise([start, *way, end]))
            if nearest[0] >= self.g.clearance_mm:
                return "round", way, nearest
            if nearest[0] > best[2][0]:
                best = ("tight", way, nearest)
        return best

    # ------------------------------------------------------------------ planning
    def candidates(self, overlap: float) -> tuple[list[Candidate], int]:
        """The usable views and how many were tried; :attr:`seen_by_view` and
        :attr:`seen_in_beam_by` record what the views see at all and, per tracker station,
        where it would see the SMR (the unmeasured surface's reasons)."""
        g = self.g
        self.dropped_too_near = 0  # views dropped for a cell object or the part too near
        self.seen_by_view = np.zeros(len(self.points), bool)
        self.seen_in_beam_by: dict[str, np.ndarray] = {}
        step = (1.0 - overlap) * min(g.field_mm)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
        pcd.normals = o3d.utility.Vector3dVector(self.normals)
        patches = pcd.voxel_down_sample(step / 2)
        centres, normals = np.asarray(patches.points), np.asarray(patches.normals)
        out: list[Candidate] = []
        tried = 0
        seed = None
        for c, n in zip(centres, normals, strict=True):
            for view in _tilted(-n / np.linalg.norm(n), *g.view_tilts_deg):
                T = look_at_flange(c, view, g.standoff_mm, g.rig_mid_in_flange)
                if g.below_floor(T):
                    continue  # not a view at all: no robot takes the scanner there
                sees = self.seen(T)
                if sees.sum() < 20:
                    continue
                self.seen_by_view |= sees
                found = self._in_sight(T)  # from home, else the first tracker station
                if found is None:
                    tried += 1
                    continue
                tracker, T, smrs, sign = found
                # a bar, a nest, a fixture, the part itself
                if self.too_near(T, sign if self.ecs == "j6" else None):
                    self.dropped_too_near += 1
                    tried += 1
                    continue
                if smrs:
                    sees = self.seen(T)  # the roll turns the field about the view
                self.seen_in_beam_by.setdefault(tracker, np.zeros(len(self.points), bool))
                self.seen_in_beam_by[tracker] |= sees
                for rail in g.rail_nearest(c):
                    tried += 1
                    q = self.reachable(T, seed, rail, sign)
                    if q is not None:
                        seed = q
                        out.append(Candidate(f"c{tried}", q, c, view, sees, sign, rail,
                                             smrs, tracker))
                        break
        return out, tried

    def _in_sight(self, T: np.ndarray
                  ) -> tuple[str, np.ndarray, tuple[str, ...], float] | None:
        """The first tracker station (home first) that sees the scanner's SMR(s) at view ``T``:
        its name, the view (rolled for the cluster), the SMRs in sight (cluster) and the J6
        turn direction (j6; 1 for the cluster)."""
        for name, head in self.trackers.items():
            if self.ecs == "cluster":
                rolled = self._cluster_roll(T, head)
                if rolled is not None:
                    return name, rolled[0], tuple(rolled[1]), 1.0
            else:
                sign = self._j6_sign(T, head)
                if sign is not None:
                    return name, T, (), sign
        return None

    def plan(self, coverage: float = 0.90, overlap: float = 0.25, name: str = "plan",
             max_stations: int | None = None, speed: float = 0.2) -> tuple[Plan, PlanReport]:
        """``speed``: the arm's between stations, a fraction of its joints' maximum speeds (the
        plan's; it orders the stations by the moves' time)."""
        cands, tried = self.candidates(overlap)
        if not cands:
            raise PlanningError(f"none of {tried} candidate views is reachable with the tracker "
                                f"seeing {'3 SMRs' if self.ecs == 'cluster' else 'the SMR'}: is "
                                f"the part in reach of the robot (world frame, mm)?")
        min_gain = max(5, int(np.ceil(MIN_GAIN_MM2 / self.area_per_sample_mm2)))
        chosen, used = self._greedy(cands, coverage, min_gain, max_stations)
        zero = np.zeros(len(self.points), bool)
        possible = np.any([zero, *(c.sees for c in cands if c.tracker in used)], axis=0)
        toured = [c for t in used
                  for c in self._toured([c for c in chosen if c.tracker == t], speed)]
        kept_at, routes = self.routed([(c.q, c.rail_mm) for c in toured], speed)
        dropped = len(toured) - len(kept_at)
        toured = [toured[i] for i in kept_at]
        kept = {id(c) for c in toured}
        curve, covered = [], zero.copy()
        for c in chosen:  # in the order chosen, before the tour reorders them
            if id(c) in kept:
                covered |= c.sees
                curve.append(float(covered[possible].mean()))
        chosen = toured
        names = [f"s{i + 1:02d}" for i in range(len(chosen))]
        moves: dict[str, int] = {}
        tight: list[dict[str, Any]] = []
        vias: list[tuple[Via, ...]] = []
        for i, (how, via, (near, what)) in enumerate(routes):
            if how == "tight":
                tight.append({"from": names[i - 1], "to": names[i], "via": len(via),
                              "nearest_mm": round(near, 1), "to_what": what})
            if how != "start":
                moves[how] = moves.get(how, 0) + 1
            vias.append(_vias(via))
        if dropped:
            moves["dropped"] = dropped
        park_vias: list[tuple[Via, ...]] = [()] * len(chosen)
        park_unclear: set[str] = set()
        if self.g.park_joints_deg is not None:  # a scanner check leaves a station by it
            park = np.radians(self.g.park_joints_deg)
            park_vias = []
            for station, c in zip(names, chosen, strict=True):
                how, via, (near, what) = self.route((c.q, c.rail_mm), (park, c.rail_mm), speed)
                moves[f"park_{how}"] = moves.get(f"park_{how}", 0) + 1
                if how == "tight":
                    tight.append({"from": station, "to": "park", "via": len(via),
                                  "nearest_mm": round(near, 1), "to_what": what})
                    park_unclear.add(station)
                park_vias.append(_vias(via))
        stations = tuple(PlanStation(names[i], tuple(float(v) for v in np.degrees(c.q)),
                                     c.rail_mm, None, int(c.j6_sign), tracker=c.tracker,
                                     via=vias[i], park_via=park_vias[i],
                                     park_clear=names[i] not in park_unclear)
                         for i, c in enumerate(chosen))
        overlaps = []
        if len(chosen) > 1:
            S = _sees_matrix(chosen)
            n = np.asarray(S.sum(axis=1)).ravel()
            shares = (S @ S.T).toarray() / np.minimum(n[:, None], n[None, :])
            np.fill_diagonal(shares, -np.inf)
            last = len(chosen) - 1 - np.argmax(shares[:, ::-1], axis=1)  # ties: the later one
            overlaps = [(stations[i].name, stations[j].name, float(shares[i, j]))
                        for i, j in enumerate(last)]
        missed = ~covered
        # by the tracker stations the plan uses: what another station would see is "beam"
        in_beam = np.any([zero, *(self.seen_in_beam_by.get(t, zero) for t in used)], axis=0)
        reasons = {"beam": missed & self.seen_by_view & ~in_beam,
                   "reach": missed & in_beam & ~possible,
                   "view": missed & ~self.seen_by_view,
                   "overlap": missed & possible}
        trackers = {t: TrackerStation(t, tuple(float(v) for v in self.trackers[t]))
                    for t in used[1:]}
        report = PlanReport(len(stations), float(covered[possible].mean()),
                            float(possible.mean()), overlaps, tried, len(cands),
                            {"share": float(missed.mean()),
                             **{k: float(reasons[k].mean()) for k in UNMEASURED_REASONS}},
                            {t: [float(v) for v in self.trackers[t]]
                             for t in [HOME_TRACKER, *trackers]}, curve, moves, tight)
        extra = report.to_json()
        del extra["coverage_curve"]  # a station's worth a value: the JSON report has it
        if self.ecs == "cluster":
            extra["smrs_in_sight"] = {st.name: list(c.smrs)
                                      for st, c in zip(stations, chosen, strict=True)}
        plan = Plan(name, stations, j6_angles_deg=self.g.j6_angles_deg, speed=speed,
                    extra=extra, ecs=self.ecs, trackers=trackers,
                    park_joints_deg=self.g.park_joints_deg)
        return plan, report

    def _greedy(self, cands: list[Candidate], coverage: float, min_gain: int,
                max_stations: int | None) -> tuple[list[Candidate], list[str]]:
        """The views chosen one by one until ``coverage`` of what the views see, and the
        tracker stations they use (home first). Each step takes the view of most new coverage,
        ranked first by how it overlaps the stations chosen so far (its largest overlap with one
        of them): the paper's 10-40 % first, then near it (5-60 %), then anything. A view from
        a tracker station not used yet scores MOVE_DISCOUNT of its gain, and only while moves
        are left. The views' samples are a sparse matrix: a view's new coverage and its overlap
        with the stations chosen are its row's products (a loop over views and chosen stations
        took most of the car body's planning)."""
        S = _sees_matrix(cands)
        n = np.maximum(1.0, np.asarray(S.sum(axis=1)).ravel())
        trackers = np.array([c.tracker for c in cands])
        possible = np.asarray(S.sum(axis=0)).ravel() > 0
        covered = np.zeros(S.shape[1], bool)
        overlap = np.zeros(len(cands))  # the largest share of a view one chosen station sees
        alive = np.ones(len(cands), bool)
        chosen: list[int] = []
        used = [HOME_TRACKER]
        while (covered[possible].mean() < coverage and alive.any()
               and (max_stations is None or len(chosen) < max_stations)):
            in_use = np.isin(trackers, used)
            weight = np.where(in_use, 1.0, MOVE_DISCOUNT)
            gain = S @ (~covered).astype(np.float64)
            score = weight * gain
            if chosen:
                score = np.where((overlap >= 0.10) & (overlap <= 0.40), 2e9 + score,
                                 np.where((overlap >= 0.05) & (overlap <= 0.60), 1e9 + score,
                                          score))
            ok = alive & (in_use | (len(used) <= self.tracker_moves)) & (gain >= min_gain)
            score = np.where(ok, score, -1.0)
            best = int(np.argmax(score))
            if score[best] < 0:
                break
            chosen.append(best)
            alive[best] = False
            row = S[best]
            covered[row.indices] = True
            overlap = np.maximum(overlap, (S @ row.T).toarray().ravel() / n)
            if trackers[best] not in used:
                used.append(str(trackers[best]))
        return [cands[i] for i in chosen], used

    def routed(self, poses: list[Pose], speed: float, drop: bool = True
               ) -> tuple[list[int], list[tuple[str, list[Pose], tuple[float, str]]]]:
        """The stations at ``poses``, in order, each with the way it is reached from the one
        before (:meth:`route`; the first: "start", no poses): the indices kept and their ways.
        With ``drop``, a station that no way reaches within ``clearance_mm`` is left out when
        the move past it to the next keeps it, up to :data:`MAX_DROPPED_IN_A_ROW` (a pocket
        between a sill and the floor that the arm cannot enter without sweeping the scanner
        into the part)."""
        kept, ways = [0], [("start", [], (np.inf, ""))]
        i = 1
        while i < len(poses):
            way = self.route(poses[kept[-1]], poses[i], speed)
            for skip in range(1, MAX_DROPPED_IN_A_ROW + 1) if drop else ():
                if way[0] != "tight" or i + skip >= len(poses):
                    break
                past = self.route(poses[kept[-1]], poses[i + skip], speed)
                if past[0] != "tight":
                    i, way = i + skip, past
            kept.append(i)
            ways.append(way)
            i += 1
        return kept, ways

    def _toured(self, cands: list[Candidate], speed: float) -> list[Candidate]:
        def seconds(a: Candidate, b: Candidate) -> float:
            rail = abs((a.rail_mm or 0.0) - (b.rail_mm or 0.0)) / self.g.rail_speed_mm_s
            return max(self.g.robot.travel_time(a.q, b.q, speed), rail)

        cost = np.array([[seconds(a, b) for b in cands] for a in cands]).reshape(len(cands), -1)
        return [cands[i] for i in _tour(cost)]


def _vias(poses: list[Pose]) -> tuple[Via, ...]:
    return tuple(Via(tuple(float(v) for v in np.degrees(q)), rail) for q, rail in poses)


def _at(poses: list[Pose], k: int) -> Pose | None:
    return poses[k] if k < len(poses) else None


def _closed_and_outward(mesh: o3d.geometry.TriangleMesh) -> bool:
    """Whether the mesh bounds a solid, wound outward: its area vectors sum to nothing (a
    closed surface's flux of a constant field) and its signed volume is positive."""
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])  # 2 x area vectors
    area = float(np.linalg.norm(cross, axis=1).sum())
    volume = float(np.einsum("ij,ij->i", v[t[:, 0]], cross).sum())  # 6 x signed volume
    return float(np.linalg.norm(cross.sum(axis=0))) < 1e-6 * area and volume > 0


def _sees_matrix(cands: list[Candidate]):
    """(views, samples) sparse 0/1 matrix of what each view sees."""
    from scipy import sparse

    cols = [np.flatnonzero(c.sees) for c in cands]
    rows = np.repeat(np.arange(len(cands)), [len(c) for c in cols])
    return sparse.csr_matrix((np.ones(len(rows)), (rows, np.concatenate(cols))),
                             shape=(len(cands), len(cands[0].sees)))


def _tour(cost: np.ndarray) -> list[int]:
    """An open path through every point from point 0, short in ``cost`` (N, N: what going from
    i to j costs): nearest neighbour, then while one shortens it, reverse a stretch (2-opt) or
    move a stretch of up to three points elsewhere, either way round (or-opt)."""
    n = len(cost)
    if n == 0:
        return []
    left = set(range(1, n))
    order = [0]
    while left:
        k = min(left, key=lambda j: (cost[order[-1], j], j))
        order.append(k)
        left.remove(k)

    def length(o: list[int]) -> float:
        return float(cost[o[:-1], o[1:]].sum())

    def neighbours(o: list[int]):
        for i in range(1, n - 1):
            for j in range(i + 1, n):
                yield o[:i] + o[i:j + 1][::-1] + o[j + 1:]
        for size in (1, 2, 3):
            for i in range(1, n - size + 1):
                stretch, rest = o[i:i + size], o[:i] + o[i + size:]
                for at in range(1, len(rest) + 1):
                    if at != i:
                        yield rest[:at] + stretch + rest[at:]
                        yield rest[:at] + stretch[::-1] + rest[at:]

    best = length(order)
    improved = True
    while improved:
        improved = False
        for o in neighbours(order):
            if (cand := length(o)) < best - 1e-9:
                order, best, improved = o, cand, True
                break
    return order
