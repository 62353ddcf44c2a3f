"""The simulated cell: world model, sensors and ground truth.

World = the laser tracker's frame (tracker at the origin, z up), mm. The tracker stands on its
tripod behind the robot with its head 1.2 m above the floor (world z = -1200 mm is the floor).
The robot base stands at ``T_world_from_rail0`` moved by the linear rail (external axis, along
world y); the part is in front of the robot (+x), facing it. The scanner is rigidly mounted on
the flange at the true hand-eye ``T_flange_from_mcs``; the SMR sits on the scanner base, off the
J6 axis so that J6 rotations move it on a circle, its opening facing backwards along the
scanner's axis (towards the tracker) so that those rotations keep it in the tracker's sight.

Everything random comes from generators seeded by ``seed``: the same seed and the same sequence
of calls give identical images and measurements.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import open3d as o3d
from scancell.model.cell_geometry import DEFAULT_VIEW_TILTS_DEG
from scancell.model.ecs import ecs_from_points
from scancell.model.patterns import FringeSequence
from scancell.model.rail_path import RailModule, RailPath
from scancell.model.robot_model import RobotModel
from scancell.model.transforms import apply_T, look_at_flange, make_T, rot_x, rot_y
from scancell.protocols.plan import DEFAULT_J6_ANGLES_DEG
from scancell.sim import mechanics as mech
from scancell.sim import parts
from scancell.sim.clock import SimClock
from scancell.sim.optics import FocalGrowthRays, PinholeModel, StereoRig, default_rig
from scancell.sim.optics_profile import (
    DEFAULT_PROFILE,
    OpticsProfile,
    defocus_px_per_unit,
    level_light,
    optics_profile,
    response_harmonics,
)
from scancell.sim.render_kernels import (
    blend_levels,
    pattern_dn,
    projector_terms,
    quantise,
    sensor_dn,
    shadowed,
    surface_terms,
)
from scancell.sim.scene import Scene, SceneObject
from scancell.sim.sensor_noise import NoiseBank
from scancell.sim.tracker_model import BeamBreak, TrackerModel, TrackerReading, TrackerSpec

#: pattern indices below this show a uniform level: ``UNIFORM_BASE - v`` for the 8-bit value v
#: (what a projector-response calibration projects); -1 dark and -2 full white are v = 0, 255
UNIFORM_BASE = -3
#: a point lit by the projector may lie this far (mm) behind its shadow map's samples: the
#: clearance the per-pixel shadow rays left at the surface and at the projector (2 x 0.05 mm)
SHADOW_TOLERANCE_MM = 0.1
#: how far the scanner's housing reaches round the optical centres of its cameras and projector
#: (mm): ``sim.parts.scanner_body`` stands 60 mm beyond the left camera, 55 mm either side of
#: the baseline and 67 mm beyond the right camera. A move that brings an optical centre nearer
#: the part than this drives the housing into it.
HOUSING_REACH_MM = 60.0

#: how far (mm) an optical centre may travel between two poses of a move's collision check: a
#: sixth of the housing's reach, so the housing cannot pass a sheet unseen
SWEEP_STEP_MM = 10.0


def uniform_level(k: int) -> float:
    """Relative level (0 … 1) of a uniform pattern index k < 0."""
    if k == -1:
        return 0.0
    if k == -2:
        return 1.0
    return (UNIFORM_BASE - k) / 255.0


#: a per-pixel blur spanning more than this (largest sigma > 2 x smallest + 1 px) gets levels
#: each at most this factor above the last (or 0.5 px): a camera with a surface a few cm from
#: its lens sees sigmas of 0.55 to 41 px, and four levels spread evenly left the in-focus
#: pixels blended between the 0.55 and the 14 px images
BLUR_LEVEL_RATIO = 1.5
#: levels above this sigma (px) are blurred on an image reduced by about sigma / 4
REDUCED_BLUR_FROM_PX = 8.0


def blur_levels(lo: float, hi: float) -> np.ndarray:
    """The sigmas (px) an image is blurred at for a per-pixel blur between ``lo`` and ``hi``."""
    if hi <= 2.0 * lo + 1.0:
        return np.linspace(lo, hi, 4 if hi - lo > 1.0 else 3)
    levels = [lo]
    while levels[-1] < hi:
        levels.append(min(hi, max(levels[-1] + 0.5, levels[-1] * BLUR_LEVEL_RATIO)))
    return np.array(levels)


def gaussian_blur(dn: np.ndarray, sigma: float, out: np.ndarray) -> None:
    """``dn`` blurred by a Gaussian of ``sigma`` px into ``out``. From ``REDUCED_BLUR_FROM_PX``
    on, on the image reduced f = sigma // 4 times (an f x f box average, then the Gaussian, then
    linear interpolation back: their variances (f² − 1)/12 + s² f² + f²/6 add up to sigma²;
    the reduced Gaussian of ~4 px removes what the reduction folds below its Nyquist limit);
    at 41 px the full-size blur took 0.2 s an image."""
    if sigma < 0.05:
        out[...] = dn
    elif sigma < REDUCED_BLUR_FROM_PX:
        cv2.GaussianBlur(dn, (0, 0), float(sigma), dst=out)
    else:
        f = int(sigma // 4)
        h, w = dn.shape
        small = cv2.resize(dn, (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA)
        s = math.sqrt(max(sigma ** 2 - (f * f - 1) / 12.0 - f * f / 6.0, 0.25)) / f
        cv2.resize(cv2.GaussianBlur(small, (0, 0), s), (w, h), dst=out,
                   interpolation=cv2.INTER_LINEAR)


def _blur(dn: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Gaussian blur with a per-pixel sigma (px): the image blurred at a few sigmas spanning the
    map (:func:`blur_levels`), blended linearly per pixel between the two nearest
    (depth-dependent defocus)."""
    lo, hi = float(np.min(sigma)), float(np.max(sigma))
    if hi < 0.05:
        return dn
    if hi - lo < 0.05 * hi + 0.02:
        return cv2.GaussianBlur(dn, (0, 0), max(0.5 * (lo + hi), 1e-3))
    levels = blur_levels(lo, hi)
    blurred = np.empty((len(levels), *dn.shape), np.float32)
    for i, s in enumerate(levels):
        gaussian_blur(dn, float(s), blurred[i])
    if np.allclose(np.diff(levels), levels[1] - levels[0]):
        pos = (sigma - lo) / np.float32(levels[1] - levels[0])
    else:
        pos = np.interp(sigma, levels, np.arange(len(levels)))
    pos = np.clip(pos, 0, len(levels) - 1 - 1e-4)
    return blend_levels(blurred, pos.astype(np.float32))


def _half_angle(rays: np.ndarray) -> float:
    """Half-angle (rad) of the cone about a device's optical axis (+z) holding its unit rays
    (..., 3), a little wider than the widest."""
    return math.acos(max(-1.0, float(rays[..., 2].min()))) + 1e-4


def _unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, float) / np.linalg.norm(v)


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def rig_bisector(rig: StereoRig) -> np.ndarray:
    """Unit vector in MCS halfway between the two cameras' optical axes (the scanner's axis)."""
    z_left = np.array([0.0, 0.0, 1.0])
    z_right = rig.T_mcs_from_right[:3, 2]
    return (z_left + z_right) / np.linalg.norm(z_left + z_right)


def default_mount(rig: StereoRig) -> np.ndarray:
    """True hand-eye ``T_flange_from_mcs``: the rig's bisector along the flange z axis, 180 mm in
    front of the flange, with a few tenths of a degree of mounting error on purpose."""
    # rig frame seen from MCS: midway between the cameras, z along the bisector
    right_origin = rig.T_mcs_from_right[:3, 3]
    bis = rig_bisector(rig)
    x = right_origin / np.linalg.norm(right_origin)
    x = x - bis * np.dot(x, bis)
    x /= np.linalg.norm(x)
    y = np.cross(bis, x)
    T_mcs_from_rig = make_T(np.stack([x, y, bis], axis=1), right_origin / 2)
    T_flange_from_rig = make_T(_rot_z(0.4) @ rot_y(-0.7) @ rot_x(1.3), [1.2, -0.8, 180.0])
    return T_flange_from_rig @ np.linalg.inv(T_mcs_from_rig)


#: the floor's height in world (the tracker's head stands 1.2 m above it), mm
FLOOR_Z_MM = -1200.0

#: the simulated cell's reference nests (world, mm): on the floor and on stands around the part,
#: in the tracker's sight past the robot and the part
DEFAULT_NESTS: dict[str, tuple[float, float, float]] = {
    "N1": (1500.0, -2300.0, -1150.0), "N2": (1500.0, 2300.0, -1150.0),
    "N3": (4600.0, -2400.0, -700.0), "N4": (4600.0, 2400.0, -700.0),
    "N5": (2800.0, -2900.0, 400.0), "N6": (2800.0, 2900.0, 400.0),
}

#: the scanner-check ball bar: centre and axis (world), off the part's side
CHECK_BAR = "check_bar"
DEFAULT_CHECK_BAR = ((3250.0, -1250.0, -250.0), (0.0, 0.8, 0.6))


@dataclass
class SimCellConfig:
    seed: int = 0
    camera_scale: float = 1.0  # 1 = 2448 x 2048; tests use 8 (306 x 256)
    part: str | None = "car_rear"
    T_world_from_part: np.ndarray = field(default_factory=lambda: make_T(t=[3300.0, 0.0, -100.0]))
    T_world_from_rail0: np.ndarray = field(default_factory=lambda: make_T(t=[1800.0, 0.0, -1200.0]))
    rail_axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    rail_limits_mm: tuple[float, float] = (-1500.0, 1500.0)
    #: the track's modules from rail 0 along ``rail_axis`` (empty: a straight rail)
    rail_path: tuple[RailModule, ...] = ()
    #: the rail positions the cell's planner may use (mm)
    rail_positions_mm: tuple[float, ...] = (-800.0, -400.0, 0.0, 400.0, 800.0)
    #: where a moved tracker may stand (world, mm; the planner's ``tracker_stations_mm``)
    tracker_stations_mm: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    #: the planner's view tilts from a patch's normal (deg)
    view_tilts_deg: tuple[float, ...] = DEFAULT_VIEW_TILTS_DEG
    #: what the scanner looks at when the cell starts (world, mm); None: the part's origin
    start_target_world: tuple[float, float, float] | None = None
    joint_repeatability_deg: float = 0.002  # 1 sigma per joint (~±0.07 mm at the flange)
    j6_repeatability_deg: float = 0.003  # extra 1 sigma on J6 (the ECS rotations)
    j6_angles_deg: tuple[float, float] = DEFAULT_J6_ANGLES_DEG  # J6 turns for P2 and P3
    smr_in_mcs_mm: np.ndarray = field(default_factory=lambda: np.array([276.0, 95.0, -140.0]))
    #: None: backwards along the rig's bisector (how the nest is machined into the housing)
    smr_opening_in_mcs: np.ndarray | None = None
    #: projector, cameras, paints and ambient light (sim/optics_profile.py, docs/explanation/simulation.md)
    optics: OpticsProfile = field(default_factory=lambda: optics_profile(DEFAULT_PROFILE))
    #: exposure time (s) at which ``optics.exposure`` holds (the cameras' nominal 10 ms)
    nominal_exposure_s: float = 0.01
    tracker: TrackerSpec = field(default_factory=TrackerSpec)
    #: compliance, vibration, drift, tracker systematics, warm-up (sim/mechanics.py)
    mechanics: mech.MechanicsProfile = field(
        default_factory=lambda: mech.mechanics_profile(mech.DEFAULT_PROFILE))
    #: fixed SMR nests (world, mm), their openings facing the tracker: the drift references
    nests_world_mm: dict[str, tuple[float, float, float]] = field(
        default_factory=lambda: dict(DEFAULT_NESTS))
    home_deg: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, -90.0, 0.0)
    #: SMR nests on the scanner's housing besides its rear SMR (issue 19): name -> (centre in
    #: mcs, opening direction in mcs); the tracker targets them as ``scanner:<name>``
    smr_cluster: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = field(
        default_factory=dict)
    #: how far each cluster nest sits off its drawing (1-sigma per axis, mm): what the hand-eye
    #: job's cluster calibration has to find
    smr_cluster_build_mm: float = 0.2
    #: the scanner-check ball bar fixed in the cell beside the part (world, mm): its centre
    #: and its axis; None: none. Where ``[metrology.scanner_check]`` of sim.toml looks.
    check_bar_world: tuple[tuple[float, float, float], tuple[float, float, float]] | None = (
        DEFAULT_CHECK_BAR)
    #: a JSON-lines file every ray cast of the left camera (MCS) appends its true pose to: what
    #: a recording cannot hold, to tell a station's pose error from its scan's (None: none)
    true_pose_log: str | None = None

    @classmethod
    def for_part(cls, part: str | None, **kwargs: Any) -> SimCellConfig:
        """The cell laid out for ``part`` (sim/layouts.py), with ``kwargs`` on top."""
        from scancell.sim.layouts import cell_layout

        return cls(part=part, **{**cell_layout(part), **kwargs})


class CollisionError(ValueError):
    """A move would drive the scanner's housing into the part: the arm does not go there."""


@dataclass
class CameraGeometry:
    """Per-pixel result of one ray cast from one camera at one pose; shared by all patterns."""

    hit: np.ndarray  # (H, W) bool
    rays: np.ndarray  # (H, W, 3) float32 unit rays of the pixels, camera frame
    t_hit: np.ndarray  # (H, W) float32 distance (mm) along each ray to its hit, inf where none
    proj_x: np.ndarray  # (H, W) projector column, NaN where not lit
    base_dn: np.ndarray  # (H, W) DN from ambient light
    fringe_dn: np.ndarray  # (H, W) DN per unit projector intensity (0 where shadowed)
    sigma_projector: np.ndarray  # (H, W) projector defocus blur at the surface, projector px
    sigma_camera: np.ndarray  # (H, W) camera blur (in-focus PSF and depth of field), px
    #: a number no other geometry of this cell has (keys the images rendered from it)
    serial: int = 0

    @property
    def points_cam(self) -> np.ndarray:
        """(H, W, 3) float64 hit points in the camera frame (mm), NaN where no hit."""
        return np.multiply(self.rays, np.where(self.hit, self.t_hit, np.nan)[..., None],
                           dtype=np.float64)


class SimCell:
    def __init__(self, cfg: SimCellConfig | None = None, rig: StereoRig | None = None) -> None:
        self.cfg = cfg or SimCellConfig()
        full_rig = rig or default_rig()
        #: the cold scanner's rig; ``self.rig`` is the rig at the current sim time (warm-up)
        self.rig_cold = (full_rig if self.cfg.camera_scale == 1
                         else full_rig.scaled(self.cfg.camera_scale))
        self.rig = self.rig_cold
        self._rig_scales = (1.0, 1.0)
        self._rig_version = 0
        self.robot = RobotModel()
        self.T_flange_from_mcs = default_mount(full_rig)
        self.smr_opening_in_mcs = (-rig_bisector(full_rig) if self.cfg.smr_opening_in_mcs is None
                                   else np.asarray(self.cfg.smr_opening_in_mcs, float))
        self._rng = np.random.default_rng([self.cfg.seed, 1])
        self.clock = SimClock()
        self.mech = self.cfg.mechanics
        self.tracker = TrackerModel(self.cfg.tracker, np.random.default_rng([self.cfg.seed, 2]),
                                    mechanics=self.mech, seed=self.cfg.seed)
        self._vib_rng = np.random.default_rng([self.cfg.seed, 6])
        self.move_end_s = -np.inf  # no ringing before the first move
        self._ring_dir = np.zeros(3)
        self._hold_dir = _unit(self._vib_rng.normal(size=3))
        self._hold_phase = float(self._vib_rng.uniform(0, 2 * np.pi))
        self._frame = 0
        self._noise = NoiseBank([self.cfg.seed, 3])
        self.q_commanded = np.radians(np.asarray(self.cfg.home_deg, float))
        self.q = self.q_commanded.copy()
        self.rail_mm = 0.0
        #: where the rail is moving to (mm), while it moves (set by its drive's emulator)
        self.rail_target_mm: float | None = None
        #: what the scanner's housing hit on a move's way (set by the robot's or the rail's
        #: simulator, cleared with the robot's fault), None: nothing
        self.collided: str | None = None
        self.rail = RailPath(tuple(map(float, self.cfg.rail_axis)), tuple(self.cfg.rail_path))
        self.pattern = -1  # -1: projector dark
        self.scene = Scene()
        self.precompensation: np.ndarray | None = None
        #: the cluster as built: each nest off its drawn centre by the housing's machining and
        #: the nest's seating (``cfg.smr_cluster_build_mm``, 1-sigma per axis; seeded)
        build = np.random.default_rng([self.cfg.seed, 11])
        self.smr_cluster = {
            n: (np.asarray(c, float) + build.normal(0.0, self.cfg.smr_cluster_build_mm, 3),
                np.asarray(o, float) / np.linalg.norm(o))
            for n, (c, o) in self.cfg.smr_cluster.items()}
        if self.cfg.part:
            mesh = parts.PARTS[self.cfg.part]()
            self.scene.add(SceneObject(self.cfg.part, mesh, self.cfg.T_world_from_part,
                                       self.cfg.optics.uniform_paint.kd,
                                       regions=parts.paint_regions(self.cfg.part, mesh)))
        self._body = self.scene.add(SceneObject("scanner_body", parts.scanner_body(), np.eye(4),
                                                visible_to_cameras=False))
        for name, c in self.cfg.nests_world_mm.items():
            self.scene.add(SceneObject(f"nest_{name}", parts.smr(), self._facing_tracker(c), 0.75))
        if self.cfg.check_bar_world is not None:
            self.scene.add(SceneObject(CHECK_BAR, parts.ARTEFACTS["ballbar"](),
                                       self.check_bar_pose(*self.cfg.check_bar_world), 0.6))
        self._ray_grids: dict[str, FocalGrowthRays] = {}  # cold cameras, built on first use
        self._rays: dict[str, np.ndarray] = {}  # at the rig's current warm-up
        #: per camera (and the projector's shadow map): pose key, versions, joints, time, value
        self._geom_cache: dict[str, tuple[bytes, tuple[int, int], bytes, float, Any]] = {}
        self._projector_rays: np.ndarray | None = None  # the shadow map's, projector frame
        self._dn_cache: dict[str, dict[tuple[int, int, int], np.ndarray]] = {}
        self._serial = 0  # geometries and loaded sequences, for the image cache
        self.load_sequence(FringeSequence())
        self._scene_version = 0
        self.timings: dict[str, float] = {}
        self._update_body()

    # ------------------------------------------------------------------ poses (ground truth)
    @property
    def T_world_from_base(self) -> np.ndarray:
        return self.rail.base_at(self.cfg.T_world_from_rail0, self.rail_mm)

    def T_world_from_flange(self, q_rad: np.ndarray | None = None) -> np.ndarray:
        """The flange's true pose: at joints ``q_rad`` at rest (the arm bent by the payload and
        grown by its warmth), or (``None``) now, vibrating."""
        if q_rad is not None:
            return self._static_flange(q_rad)
        return self._flange_now(self.clock.now())

    def _static_flange(self, q_rad: np.ndarray) -> np.ndarray:
        q = np.asarray(q_rad, float)
        base = self.T_world_from_base
        dq = mech.compliance_deflection(lambda x: base @ self.robot.fk(x), q, self.mech)
        T = self.robot.fk(q + dq)
        T[:3, 3] *= 1.0 + mech.robot_growth(self.clock.now(), self.mech)
        return base @ T

    def _flange_now(self, t_s: float, window_s: float = 0.0) -> np.ndarray:
        """The flange at sim time ``t_s`` with the arm's vibration (averaged over ``window_s``)."""
        T = self._static_flange(self.q)
        T[:3, 3] += (mech.ring_offset(t_s + window_s / 2 - self.move_end_s, self._ring_dir,
                                      self.mech)
                     + mech.hold_offset(t_s, self._hold_dir, self._hold_phase, self.mech,
                                        window_s))
        return T

    def T_world_from_mcs(self, q_rad: np.ndarray | None = None) -> np.ndarray:
        return self.T_world_from_flange(q_rad) @ self.T_flange_from_mcs

    def T_world_from_camera(self, camera: str, q_rad: np.ndarray | None = None) -> np.ndarray:
        T = self.T_world_from_mcs(q_rad)
        if camera == "left":
            return T
        if camera == "right":
            return T @ self.rig.T_mcs_from_right
        if camera == "projector":
            return T @ self.rig.T_mcs_from_projector
        raise KeyError(f"no camera {camera!r}: use 'left', 'right' or 'projector'")

    def smr_center_world(self, q_rad: np.ndarray | None = None) -> np.ndarray:
        return apply_T(self.T_world_from_mcs(q_rad), self.cfg.smr_in_mcs_mm[None])[0]

    def smr_opening_world(self, q_rad: np.ndarray | None = None) -> np.ndarray:
        return self.T_world_from_mcs(q_rad)[:3, :3] @ self.smr_opening_in_mcs

    def mcs_pose_looking_at(self, target_world: np.ndarray, standoff_mm: float = 650.0,
                            view_dir: np.ndarray | None = None) -> np.ndarray:
        """``T_world_from_mcs`` that puts ``target_world`` on the rig's bisector (the flange z
        axis), ``standoff_mm`` in front of the midpoint between the cameras, looking along
        ``view_dir`` (default world +x) with the baseline horizontal."""
        v = np.array([1.0, 0, 0]) if view_dir is None else np.asarray(view_dir, float)
        T_fm = self.T_flange_from_mcs
        rig_mid_in_flange = T_fm[:3, 3] + T_fm[:3, :3] @ (self.rig.T_mcs_from_right[:3, 3] / 2)
        T_world_from_flange = look_at_flange(target_world, v, standoff_mm, rig_mid_in_flange)
        return T_world_from_flange @ T_fm

    def start_joints(self, down_deg: float = 20.0) -> np.ndarray:
        """Joints (rad) with the scanner looking at the part (its centre, or the layout's start
        target), away from the tracker and ``down_deg`` down from the horizontal: the part is in
        view, the SMR faces the tracker, and a calibration ball in front of the scanner is seen
        by the tracker below the scanner's housing."""
        t = np.radians(down_deg)
        target = (self.cfg.T_world_from_part[:3, 3] if self.cfg.start_target_world is None
                  else np.asarray(self.cfg.start_target_world, float))
        away = (target - self.tracker.home)[:2]  # the SMR's opening faces back along the view
        away /= np.linalg.norm(away)
        return self.ik_for_mcs(self.mcs_pose_looking_at(
            target, view_dir=np.array([np.cos(t) * away[0], np.cos(t) * away[1], -np.sin(t)])))

    def ik_for_mcs(self, T_world_from_mcs: np.ndarray, seed_rad: np.ndarray | None = None
                   ) -> np.ndarray:
        """Joints (rad) that put MCS at ``T_world_from_mcs`` (raises IKError)."""
        T_base_from_flange = (np.linalg.inv(self.T_world_from_base) @ T_world_from_mcs
                              @ np.linalg.inv(self.T_flange_from_mcs))
        return self.robot.ik(T_base_from_flange, self.q if seed_rad is None else seed_rad)

    def j6_turned(self, q_rad: np.ndarray, turn_deg: float) -> np.ndarray:
        q = np.array(q_rad, float)
        q[5] += np.radians(turn_deg)
        return q

    def true_T_world_from_ecs(self, q_rad: np.ndarray | None = None,
                              j6_angles_deg: tuple[float, float] | None = None) -> np.ndarray:
        """ECS at a station, from noise-free SMR centres at J6 = q6, q6 + a1, q6 + a2."""
        q = self.q_commanded if q_rad is None else np.asarray(q_rad, float)
        a1, a2 = j6_angles_deg or self.cfg.j6_angles_deg
        p = [self.smr_center_world(self.j6_turned(q, a)) for a in (0.0, a1, a2)]
        return ecs_from_points(*p)

    def true_T_ecs_from_mcs(self, j6_angles_deg: tuple[float, float] | None = None) -> np.ndarray:
        """The true hand-eye in the paper's sense (constant for given J6 turn angles)."""
        q = np.radians(np.asarray(self.cfg.home_deg, float))
        return (np.linalg.inv(self.true_T_world_from_ecs(q, j6_angles_deg))
                @ self.T_world_from_mcs(q))

    def planner_table(self) -> dict:
        """This cell's geometry as a ``[planner]`` table (what a real cell's config states)."""
        T_fm = self.T_flange_from_mcs
        rig_mid = T_fm[:3, 3] + T_fm[:3, :3] @ (self.rig.T_mcs_from_right[:3, 3] / 2)
        return {"T_world_from_base": self.cfg.T_world_from_rail0.tolist(),  # rail at 0
                "T_flange_from_mcs": T_fm.tolist(), "rig_mid_in_flange_mm": rig_mid.tolist(),
                "smr_in_mcs_mm": self.cfg.smr_in_mcs_mm.tolist(),
                "smr_opening_in_mcs": self.smr_opening_in_mcs.tolist(),
                "tracker_world_mm": self.tracker.home.tolist(),
                "smr_acceptance_deg": self.cfg.tracker.acceptance_half_angle_deg,
                "rail_axis": self.cfg.rail_axis.tolist(),
                "rail_positions_mm": list(self.cfg.rail_positions_mm),
                **({"rail_path": self.rail.to_table()} if self.cfg.rail_path else {}),
                **({"tracker_stations_mm": {n: list(p) for n, p in
                                            self.cfg.tracker_stations_mm.items()}}
                   if self.cfg.tracker_stations_mm else {}),
                "view_tilts_deg": list(self.cfg.view_tilts_deg), "floor_z_mm": FLOOR_Z_MM,
                # the simulated drive's 500 mm/s at the speed a job moves the rail (0.5)
                "rail_speed_mm_s": 250.0,
                # as drawn: the true nests sit where the housing's machining put them
                "smr_cluster": {n: {"mcs_mm": list(c), "opening": list(o)}
                                for n, (c, o) in self.cfg.smr_cluster.items()},
                # the objects the scanner keeps clear of: the scanner-check bar (its spheres'
                # radius around its axis) and the reference nests (a 1.5" SMR's nest, 25 mm)
                "clearance_mm": 100.0,
                "obstacles": self._obstacles_table(),
                # the controller's home: the arm up, the scanner looking down at the base
                "park_joints_deg": list(self.cfg.home_deg),
                # the projector's calibration (the scanner's maker states it)
                "projector_in_mcs_mm": self.rig.T_mcs_from_projector[:3, 3].tolist()}

    def _obstacles_table(self) -> list[dict]:
        out = []
        if self.cfg.check_bar_world is not None:
            a, b = self.check_bar_ends_world()
            out.append({"name": "scanner-check bar",
                        "capsule": {"a": list(map(float, a)), "b": list(map(float, b)),
                                    "radius": 15.0}})
        out += [{"name": f"nest {n}", "sphere": {"centre": [float(v) for v in c], "radius": 25.0}}
                for n, c in self.cfg.nests_world_mm.items()]
        return out

    def part_mesh_world(self) -> o3d.geometry.TriangleMesh:
        """The part's true surface in ``world`` (mm)."""
        if not self.cfg.part:
            raise ValueError("this cell has no part")
        mesh = parts.PARTS[self.cfg.part]()
        mesh.transform(self.cfg.T_world_from_part)
        return mesh

    def surface_distance(self, points_world: np.ndarray) -> np.ndarray:
        """Unsigned distance (mm) of world points to the true surface of the part."""
        if not self.cfg.part:
            raise ValueError("this cell has no part")
        return self.scene.distance(points_world, [self.cfg.part])

    # ------------------------------------------------------------------ actuators
    def move_joints(self, q_rad: np.ndarray, duration_s: float = 0.0,
                    speed: float | None = None) -> None:
        """Arrive at ``q_rad`` (CollisionError where :meth:`collision` says the housing would
        hit the part) with the configured repeatability, ``duration_s`` of sim time
        after the move started. A joint that does not travel (less than 0.01 deg, e.g.
        commanded to its own reported position) holds where it is (``self.q``): only the joints
        that move land with fresh repeatability noise. A move that travels leaves the arm
        ringing, the more the faster it went (``speed``: its override, a fraction of the joints'
        maximum speed; None: the reference speed of the ringing's amplitude)."""
        q = np.asarray(q_rad, float).copy()
        if not self.robot.within_limits(q):
            raise ValueError(f"joints outside the limits: {np.degrees(q).round(3)} deg")
        crash = self.collision(q)
        if crash:
            raise CollisionError(f"joints {np.degrees(q).round(3)} deg: {crash}")
        noise = self._rng.normal(0, np.radians(self.cfg.joint_repeatability_deg), 6)
        noise[5] += self._rng.normal(0, np.radians(self.cfg.j6_repeatability_deg))
        moved = np.abs(q - self.q) > np.radians(0.01)
        self.clock.advance(max(duration_s, 0.0))
        self.q_commanded = q
        self.q = np.where(moved, q + noise, self.q)
        if moved.any():
            self._start_ringing(1.0 if speed is None else speed / self.mech.ring_reference_speed)
        self._update_body()

    def collision(self, q_rad: np.ndarray) -> str | None:
        """What the scanner's housing would hit at joints ``q_rad`` on the rail where it is, or
        where it is going while it moves (the part, within :data:`HOUSING_REACH_MM` of an
        optical centre), or None. As a controller's collision detection stops the arm on
        contact, the move does not happen. The way there: :meth:`path_collision`."""
        if not self.cfg.part:
            return None
        T = self.T_world_from_mcs(q_rad)
        if self.rail_target_mm is not None:  # the arm and the rail move together: where both end
            T = (self.rail.base_at(self.cfg.T_world_from_rail0, self.rail_target_mm)
                 @ np.linalg.inv(self.T_world_from_base) @ T)
        names = ("left camera", "right camera", "projector")
        centres = [T[:3, 3], *(apply_T(T, M[:3, 3][None])[0] for M in (
            self.rig.T_mcs_from_right, self.rig.T_mcs_from_projector))]
        near = self.surface_distance(np.array(centres))
        i = int(np.argmin(near))
        if near[i] >= HOUSING_REACH_MM:
            return None
        return (f"the scanner's {names[i]} would be {near[i]:.0f} mm from the part, inside its "
                f"housing's {HOUSING_REACH_MM:g} mm: a collision")

    def path_collision(self, q_from: np.ndarray, rail_from: float, q_to: np.ndarray,
                       rail_to: float) -> tuple[str, np.ndarray, float] | None:
        """Where the scanner's housing hits the part or the floor on the way from joints
        ``q_from`` (rad) at rail ``rail_from`` (mm) to ``q_to`` at ``rail_to``, both moving
        linearly (a tick of the robot's or the rail's motion): the reason, and the last joints
        and rail before it (where a controller's collision detection stops the arm); None if it
        stays clear. Samples every :data:`SWEEP_STEP_MM` of an optical centre's travel at most,
        so a sheet cannot slip between two of them."""
        if not self.cfg.part:
            return None
        q0, q1 = np.asarray(q_from, float), np.asarray(q_to, float)
        local = np.stack([np.zeros(3), self.rig.T_mcs_from_right[:3, 3],
                          self.rig.T_mcs_from_projector[:3, 3]])
        tool = float(np.linalg.norm(self.T_flange_from_mcs[:3, 3])
                     + np.linalg.norm(local, axis=1).max())
        levers = self.robot.joint_levers_mm(tool)
        travel = (np.abs(q1 - q0) @ levers
                  + abs(rail_to - rail_from) * (1.0 + self.rail.max_turn_per_mm * levers.max()))
        f = np.linspace(0.0, 1.0, max(2, int(np.ceil(travel / SWEEP_STEP_MM)) + 1))
        rail0 = self.cfg.T_world_from_rail0
        poses = [self.rail.base_at(rail0, rail_from + (rail_to - rail_from) * t)
                 @ self.robot.fk(q0 + (q1 - q0) * t) @ self.T_flange_from_mcs for t in f]
        centres = np.concatenate([local @ T[:3, :3].T + T[:3, 3] for T in poses])
        part = self.surface_distance(centres).reshape(len(f), 3)
        floor = (centres[:, 2] - FLOOR_Z_MM).reshape(len(f), 3)
        near = np.minimum(part, floor)
        hit = np.flatnonzero(near.min(axis=1) < HOUSING_REACH_MM)
        if not len(hit):
            return None
        k = int(hit[0])
        names = ("left camera", "right camera", "projector")
        i = int(np.argmin(near[k]))
        what = "the part" if part[k, i] <= floor[k, i] else "the floor"
        safe = max(k - 1, 0)
        return (f"the scanner's {names[i]} came {near[k, i]:.0f} mm from {what} on the way, "
                f"inside its housing's {HOUSING_REACH_MM:g} mm: a collision",
                q0 + (q1 - q0) * f[safe], rail_from + (rail_to - rail_from) * f[safe])

    def move_rail(self, position_mm: float, duration_s: float = 0.0, arrived: bool = True
                  ) -> None:
        """Put the rail at ``position_mm`` after ``duration_s`` of sim time; a move that
        ``arrived`` leaves the arm ringing."""
        lo, hi = self.cfg.rail_limits_mm
        if not lo <= position_mm <= hi:
            raise ValueError(f"rail position {position_mm} mm outside [{lo}, {hi}]")
        self.clock.advance(max(duration_s, 0.0))
        moved = abs(position_mm - self.rail_mm) > 1e-6
        self.rail_mm = float(position_mm)
        if moved and arrived:
            self._start_ringing()
        self._update_body()

    def _start_ringing(self, scale: float = 1.0) -> None:
        """The arm rings from now along a random direction, ``scale`` x the profile's
        amplitude."""
        self.move_end_s = self.clock.now()
        self._ring_dir = scale * _unit(self._vib_rng.normal(size=3))

    def _update_body(self) -> None:
        self._body.T_world_from_object = self.T_world_from_mcs()

    # ------------------------------------------------------------------ objects
    def place_ball(self, center_world: np.ndarray, with_stand: bool = True) -> None:
        """Put the calibration SMR on a stand at ``center_world``, opening towards the tracker."""
        self.remove_ball()
        c = np.asarray(center_world, float)
        self.scene.add(SceneObject("ball", parts.smr(), self._facing_tracker(c), 0.75))
        if with_stand:
            self.scene.add(SceneObject("ball_stand", parts.ball_stand(), make_T(t=c), 0.3))
        self._scene_version += 1

    @staticmethod
    def check_bar_pose(centre: tuple[float, ...], axis: tuple[float, ...]) -> np.ndarray:
        """T_world_from_bar of a ball bar (its axis is the dumbbell's y) facing -x of the
        world, where the robot looks from."""
        y = np.asarray(axis, float) / np.linalg.norm(axis)
        x = np.array([1.0, 0.0, 0.0]) - y[0] * y
        x /= np.linalg.norm(x)
        return make_T(np.stack([x, y, np.cross(x, y)], axis=1), np.asarray(centre, float))

    def check_bar_ends_world(self) -> np.ndarray:
        """The true centres (2, 3) of the check bar's spheres (world, mm)."""
        T = self.scene.get(CHECK_BAR).T_world_from_object
        half = parts.BALLBAR_LENGTH_MM / 2
        return np.array([T[:3, 3] + s * half * T[:3, 1] for s in (-1.0, 1.0)])

    def move_tracker(self, T_world_from_base: np.ndarray, duration_s: float = 0.0) -> None:
        """Set the tracker up at ``T_world_from_base`` (its head at the translation), taking
        ``duration_s`` of sim time; the nests' SMRs are turned to face it there, as a person
        turns an SMR in its nest (its centre stays)."""
        self.tracker.move_to(T_world_from_base)
        for name in self.cfg.nests_world_mm:
            nest = self.scene.get(f"nest_{name}")
            nest.T_world_from_object = self._facing_tracker(nest.T_world_from_object[:3, 3])
        self._scene_version += 1
        self.clock.advance(duration_s)

    def true_T_world_from_tracker(self) -> np.ndarray:
        """The frame the tracker reports in, in ``world`` now, without its stand's drift:
        ``world`` itself where it stood first."""
        return self.tracker.T_world_from_readings()

    def _facing_tracker(self, center_world: np.ndarray) -> np.ndarray:
        """The frame of an SMR at ``center_world`` whose opening (z) faces the tracker."""
        c = np.asarray(center_world, float)
        z = (self.tracker.position - c) / np.linalg.norm(self.tracker.position - c)
        x = np.cross([0.0, 0.0, 1.0], z)
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0, 0])
        return make_T(np.stack([x, np.cross(z, x), z], axis=1), c)

    def remove_ball(self) -> None:
        before = len(self.scene.objects)
        self.scene.remove("ball")
        self.scene.remove("ball_stand")
        if len(self.scene.objects) != before:
            self._scene_version += 1

    def add_object(self, obj: SceneObject) -> None:
        self.scene.add(obj)
        self._scene_version += 1

    def remove_object(self, name: str) -> None:
        self.scene.remove(name)
        self._scene_version += 1

    def ball_center_world(self) -> np.ndarray:
        return self.scene.get("ball").T_world_from_object[:3, 3].copy()

    # ------------------------------------------------------------------ tracker
    def reflectors_world(self) -> dict[str, np.ndarray]:
        """Every reflector's centre (world, mm) now: the scanner's SMR, the calibration ball if
        placed, and the nests (``nest:<name>``)."""
        out = {"scanner": self.smr_center_world()}
        T = self.T_world_from_mcs()
        for name, (c, _) in self.smr_cluster.items():
            out[f"scanner:{name}"] = T[:3, :3] @ np.asarray(c, float) + T[:3, 3]
        with contextlib.suppress(KeyError):
            out["ball"] = self.ball_center_world()
        for name in self.cfg.nests_world_mm:
            out[f"nest:{name}"] = self.scene.get(f"nest_{name}").T_world_from_object[:3, 3].copy()
        return out

    def _reflector(self, target: str, t_s: float | None = None, window_s: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
        """Centre, the SMR's rotation (its opening is the z column), opening direction and the
        self-occluding object names of a tracker target, at sim time ``t_s``."""
        if target == "scanner" or target.startswith("scanner:"):
            T = self._flange_now(self.clock.now() if t_s is None else t_s, window_s) \
                @ self.T_flange_from_mcs
            if target == "scanner":
                centre, opening = self.cfg.smr_in_mcs_mm, self.smr_opening_in_mcs
            else:
                try:
                    centre, opening = self.smr_cluster[target.removeprefix("scanner:")]
                except KeyError:
                    raise KeyError(f"unknown tracker target {target!r}: the cluster has "
                                   f"{sorted(self.cfg.smr_cluster)}") from None
            c = apply_T(T, np.asarray(centre, float)[None])[0]
            return c, T[:3, :3], T[:3, :3] @ opening, ()
        name = "ball" if target == "ball" else f"nest_{target.removeprefix('nest:')}"
        if target != "ball" and not (target.startswith("nest:")
                                     and target[5:] in self.cfg.nests_world_mm):
            raise KeyError(f"unknown tracker target {target!r}: use 'scanner', 'ball' or "
                           f"'nest:<name>' of {sorted(self.cfg.nests_world_mm)}")
        try:
            T = self.scene.get(name).T_world_from_object
        except KeyError:
            raise BeamBreak("no calibration ball in the cell") from None
        return T[:3, 3], T[:3, :3], T[:3, 2], (name,)  # an SMR does not occlude its own beam

    def find_reflector(self, approx_mm: np.ndarray) -> str | None:
        """The target FindReflector locks on for ``approx_mm`` (the tracker's frame), or None;
        the search takes ``tracker_find_s`` of sim time, found or not."""
        found = self.tracker.find(approx_mm, self.reflectors_world(), self.clock.now())
        self.clock.advance(self.mech.tracker_find_s)
        return found

    def beam_check(self, target: str = "scanner") -> None:
        """Raise BeamBreak unless the tracker can lock on ``target``; draws no noise."""
        c, _, o, exclude = self._reflector(target)
        self.tracker.beam_check(c, o, parts.SMR_RADIUS_MM, self.scene, exclude)

    def measure_smr(self, target: str = "scanner") -> TrackerReading:
        """Tracker measurement of the scanner's SMR, the calibration ball or a nest; BeamBreak
        if the beam cannot reach it. It takes one shot's sim time, over which the tracker
        averages the reflector's motion."""
        shot = self.mech.tracker_shot_s
        t0 = self.clock.now()
        c, R, o, exclude = self._reflector(target, t0, shot)
        self.tracker.beam_check(c, o, parts.SMR_RADIUS_MM, self.scene, exclude)
        self.clock.advance(shot)
        return self.tracker.measure(c, R, target, t0 + shot / 2)

    # ------------------------------------------------------------------ rendering
    def camera_model(self, camera: str) -> PinholeModel:
        return {"left": self.rig.left, "right": self.rig.right}[camera]

    def _pixel_rays(self, camera: str) -> np.ndarray:
        if camera not in self._rays:
            if camera not in self._ray_grids:
                cold = {"left": self.rig_cold.left, "right": self.rig_cold.right}[camera]
                self._ray_grids[camera] = FocalGrowthRays(cold)
            self._rays[camera] = self._ray_grids[camera].rays(self._rig_scales[1])
        return self._rays[camera]

    def geometry(self, camera: str) -> CameraGeometry:
        """Ray cast, projector mapping, shadowing and shading of one camera at the current pose
        (cached: the patterns of one pose reuse it)."""
        self._warm_rig()

        def compute(T_wc: np.ndarray) -> CameraGeometry:
            self._dn_cache.pop(camera, None)  # the old pose's images: freed before the new
            geom = self._compute_geometry(camera, T_wc)
            self._serial += 1
            geom.serial = self._serial
            if camera == "left" and self.cfg.true_pose_log:
                self._log_true_pose(T_wc)
            return geom

        return self._at_pose(camera, compute)

    def _log_true_pose(self, T_world_from_mcs: np.ndarray) -> None:
        """Append the pose the left camera's images are rendered at to ``cfg.true_pose_log``:
        host clock (ns, as the daemon's records), sim time (s), joints (deg), rail (mm) and
        ``T_world_from_mcs`` (world, mm)."""
        line = {"stamp_ns": time.time_ns(), "sim_s": self.clock.now(),
                "joints_deg": np.degrees(self.q).round(6).tolist(), "rail_mm": self.rail_mm,
                "T_world_from_mcs": T_world_from_mcs.tolist()}
        with open(self.cfg.true_pose_log, "a", encoding="utf-8") as f:
            f.write(json.dumps(line) + "\n")

    def _at_pose(self, device: str, compute: Callable[[np.ndarray], Any]) -> Any:
        """``compute(T_world_from_device)`` at the current pose, cached per device. The frames
        of one burst (a scan's patterns) share the pose of its first frame: the arm's vibration
        and thermal growth during one scan are not rendered (docs/explanation/simulation.md)."""
        now = self.clock.now()
        T = self.T_world_from_camera(device)
        key = T.round(9).tobytes()
        rest = self.q.tobytes()  # the arm's joints: the same until its next move
        versions = (self._scene_version, self._rig_version)
        cached = self._geom_cache.get(device)
        if cached and cached[1] == versions and (
                cached[0] == key or (cached[2] == rest
                                     and now - cached[3] <= self.mech.render_burst_s)):
            return cached[4]
        self._geom_cache.pop(device, None)  # freed before its successor is computed
        del cached
        value = compute(T)
        self._geom_cache[device] = (key, versions, rest, now, value)
        return value

    def _projector_depth(self) -> tuple[np.ndarray, int]:
        """The projector's shadow map at the current pose: the distance (mm, float32, inf
        where nothing) from its centre to the first surface along every ``step``-th projector
        pixel's ray, from one sample before the first pixel (-step) on, and ``step``. Both
        cameras' shadows come from it: one ray per projector sample instead of one per lit
        camera pixel and camera. Small test images sample the projector as coarsely as they
        sample the part (``step`` = camera_scale // 2)."""
        step = max(1, int(self.cfg.camera_scale) // 2)

        def compute(T_wp: np.ndarray) -> np.ndarray:
            if self._projector_rays is None:  # the projector does not warm up: rays kept
                proj = self.rig.projector
                # one sample beyond each edge: a point lit at the image's border (-0.5 px or
                # width - 0.5) lies between two samples, never beyond the last
                cols = np.arange(-1, math.ceil((proj.width - 0.5) / step) + 1) * float(step)
                rows = np.arange(-1, math.ceil((proj.height - 0.5) / step) + 1) * float(step)
                self._projector_rays = np.ascontiguousarray(proj.pixel_rays(cols, rows),
                                                            np.float32)
            rays = self._projector_rays
            hits = self.scene.cast(T_wp[:3, 3], rays.reshape(-1, 3) @ T_wp[:3, :3].T.astype(
                np.float32), cameras_only=False, cone=(T_wp[:3, 2], _half_angle(rays)))
            return hits.t.reshape(rays.shape[:2])

        return self._at_pose("projector", compute), step

    def rig_at(self, t_s: float) -> StereoRig:
        """The rig ``t_s`` seconds of sim time after power-on (the scanner's warm-up)."""
        return self.rig_cold.grown(*mech.scanner_scales(t_s, self.mech))

    def _warm_rig(self) -> None:
        """Move the rig to the scanner's warm-up state at the current sim time (baseline and
        focal lengths grow); a change under 0.5 ppm keeps the rig."""
        scales = mech.scanner_scales(self.clock.now(), self.mech)
        if max(abs(a - b) for a, b in zip(scales, self._rig_scales, strict=True)) < 0.5e-6:
            return
        self.rig = self.rig_cold.grown(*scales)
        self._rig_scales = scales
        self._rig_version += 1
        self._rays.clear()

    def _compute_geometry(self, camera: str, T_wc: np.ndarray) -> CameraGeometry:
        cfg = self.cfg
        clock = time.perf_counter
        t0 = clock()
        rays = self._pixel_rays(camera)
        t1 = clock()
        h, w, _ = rays.shape
        dirs = rays.reshape(-1, 3)
        hits = self.scene.cast(T_wc[:3, 3], dirs @ T_wc[:3, :3].T.astype(np.float32),
                               cone=(T_wc[:3, 2], _half_angle(rays)))
        t2 = clock()
        T_pc = np.linalg.inv(self.T_world_from_camera("projector")) @ T_wc
        proj = self.rig.projector
        proj_x, proj_y, cos_p, dist, cos_h = projector_terms(
            dirs, hits.t, hits.normal, T_wc[:3, :3], T_pc[:3, :3], T_pc[:3, 3],
            proj.K, proj.brown_conrady5, proj.width, proj.height)
        t3 = clock()
        depth, step = self._projector_depth()
        proj_x[shadowed(proj_x, proj_y, dist, depth, step, SHADOW_TOLERANCE_MM)] = np.nan
        t4 = clock()
        kd, lobe = self._paint(hits, cos_h)
        o = cfg.optics
        cam = self.camera_model(camera)
        # the lens's blur is a property of the full-resolution sensor; small test images see
        # it 1/camera_scale as wide
        full_f = float(cam.K[0, 0]) * cfg.camera_scale
        fringe, base, sigma_p, sigma_c = surface_terms(
            proj_x, cos_p, dist, hits.t, kd, lobe, 255.0 * o.exposure, o.ambient,
            float(np.linalg.norm(self.rig.T_mcs_from_projector[:3, 3] - [0, 0, 650.0])),
            defocus_px_per_unit(float(proj.K[0, 0]), o.projector_pitch_mm, o.projector_f_number,
                                o.projector_focus_mm), o.projector_focus_mm,
            defocus_px_per_unit(full_f, o.camera_pitch_mm, o.camera_f_number, o.camera_focus_mm),
            o.camera_focus_mm, o.psf_sigma_px, float(cfg.camera_scale))
        hit = np.isfinite(hits.t)
        self.timings = {"pixel_rays": t1 - t0, "ray_cast": t2 - t1, "projector_map": t3 - t2,
                        "shadow": t4 - t3, "shading": clock() - t4}
        return CameraGeometry(hit.reshape(h, w), rays, hits.t.reshape(h, w),
                              proj_x.reshape(h, w), base.reshape(h, w), fringe.reshape(h, w),
                              sigma_p.reshape(h, w), sigma_c.reshape(h, w))

    def _paint(self, hits, cos_h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Diffuse albedo and specular lobe (radiance factors, float32) of every hit pixel."""
        n = hits.t.shape[0]
        kd = np.zeros(n, np.float32)
        lobe = np.zeros(n, np.float32)
        table = self.cfg.optics.paint_table()
        for i, obj in enumerate(self.scene.objects):
            sel = np.flatnonzero(hits.object_index == i)
            if not sel.size:
                continue
            if obj.regions is None or self.cfg.optics.paints == "uniform":
                kd[sel] = obj.albedo
                continue
            region = obj.regions[hits.primitive[sel]]
            for r, paint in enumerate(table):
                rs = sel[region == r]
                kd[rs] = paint.kd
                if paint.ks > 0:
                    # the lobe is below 1e-6 of its peak where cos^s < 1e-6: skip those pixels
                    near = rs[cos_h[rs] > np.float32(1e-6 ** (1 / paint.shininess))]
                    lobe[near] = (paint.ks * (paint.shininess + 8) / 8
                                  * cos_h[near].astype(np.float64) ** paint.shininess)
        return kd, lobe

    def load_sequence(self, sequence: FringeSequence,
                      precompensation: np.ndarray | None = None) -> int:
        """Load fringe patterns; ``precompensation`` (256 ints): the 8-bit value the projector is
        given for each value wanted (a projector-response calibration's inverse), or None."""
        if precompensation is not None:
            lut = np.asarray(precompensation)
            if lut.shape != (256,) or lut.min() < 0 or lut.max() > 255:
                raise ValueError("precompensation must be 256 values in 0 … 255")
            precompensation = lut.astype(np.int64)
        self.sequence = sequence
        self.precompensation = precompensation
        self._serial += 1
        self._sequence_serial = self._serial
        c = response_harmonics(self.cfg.optics, sequence.A, sequence.B, precompensation)
        # harmonics below 1e-3 of full white are under a quarter of one 8-bit pattern step
        # (what a linear or pre-compensated projector leaves): not worth rendering
        keep = np.flatnonzero(np.abs(c) > 1e-3)
        self._harmonics = c[: int(keep.max()) + 1 if keep.size else 1]
        return len(sequence)

    def show(self, k: int) -> None:
        if not -3 - 255 <= k < len(self.sequence):
            raise IndexError(f"pattern {k} outside the loaded sequence of {len(self.sequence)}")
        self.pattern = k

    def render(self, camera: str, pattern: int | None = None, brightness: float = 1.0,
               gain: float = 1.0) -> np.ndarray:
        """8-bit image of ``camera`` under projector pattern ``pattern`` (default: the one shown;
        -1 dark, -2 full white, ``UNIFORM_BASE - v`` the uniform 8-bit level v);
        ``brightness`` scales the exposure (exposure time / nominal), ``gain`` the camera's
        analogue gain (linear)."""
        with self._noise.rendering():
            g = self.geometry(camera)
            k = self.pattern if pattern is None else pattern
            o = self.cfg.optics
            dn = self._irradiance(camera, g, k)
            noise = self._noise.take(dn.shape, self._frame)
            self._frame += 1
            exposure = brightness * gain
            if o.sensor_model == "emva":
                k_dn_per_e = 255.0 / o.full_well_e * gain
                dark_e = o.dark_current_e_per_s * self.cfg.nominal_exposure_s * brightness
                # the DN were at unit gain: electrons = dn / (255 / full well)
                return sensor_dn(dn, noise, k_dn_per_e, o.dark_noise_e, dark_e, exposure)
            return quantise(dn, noise, o.read_noise_dn, exposure)

    def _irradiance(self, camera: str, g: CameraGeometry, k: int) -> np.ndarray:
        """Blurred irradiance (DN at unit exposure and gain) under pattern k. Optics are linear
        in the exposure, so the exposures of an HDR scan share it (cached per camera, pose,
        scene and loaded sequence)."""
        key = (g.serial, k, self._sequence_serial)
        cache = self._dn_cache.setdefault(camera, {})
        if key in cache:
            return cache[key]
        if (cache and next(iter(cache))[0] != g.serial) or len(cache) > 2 * len(self.sequence) + 8:
            cache.clear()
        seq = self.sequence
        if k >= 0:
            j, n = seq.split(k)
            dn = pattern_dn(g.base_dn, g.fringe_dn, g.proj_x, g.sigma_projector, True,
                            seq.periods[j] / self.rig.projector.width, 2 * np.pi * n / seq.steps,
                            self._harmonics, 0.0, 1.0)
        else:
            light = level_light(self.cfg.optics, uniform_level(k))  # levels go out as they are
            dn = pattern_dn(g.base_dn, g.fringe_dn, g.proj_x, g.sigma_projector, False, 0.0, 0.0,
                            self._harmonics, light, 1.0)
        cache[key] = _blur(dn, g.sigma_camera)
        return cache[key]

    def render_sequence(self, camera: str) -> list[np.ndarray]:
        """All patterns of the loaded sequence for one camera (one ray cast)."""
        return [self.render(camera, k) for k in range(len(self.sequence))]

    def true_points(self, camera: str = "left") -> np.ndarray:
        """True surface points (N, 3) seen by ``camera``, in that camera's frame (mm)."""
        g = self.geometry(camera)
        return g.points_cam[g.hit]
