"""``cmd/job/calibrate_hand_eye``: the observations for the paper's hand-eye calibration.

At the current robot pose: the scanner's SMR measured by the tracker at J6 = q6 and at the
J6 turns (the ECS); then, for each of N positions of the calibration ball spread over the
scanner's field and depth, a coupled scan (``cmd/scan`` frames) and a tracker measurement of
the ball. When the cell's geometry names an SMR cluster on the scanner (``[planner]
smr_cluster``), the job then turns J6 through the angles at which the cluster's SMRs face the
tracker and measures them (``kind = "cluster"``): the poses the rear SMR's J6 circle gives
locate each in the scanner's frame; SMRs no J6 turn shows are measured with the scanner tipped
towards them, located through the pose the others give there. Every observation goes out
on ``calib/hand_eye/sample``; ``scancell worker calibrate`` turns them into ``T_ecs_from_mcs``
and the cluster's calibration. On the simulated cell the world places the ball (as an
operator would); on a real cell the job waits for ``cmd/job/confirm`` each time.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from scancell.analysis.smr_cluster import cluster_tilts, cluster_turns
from scancell.daemon.jobs.cluster_measure import measure_cluster
from scancell.daemon.jobs.devices import measuring_devices
from scancell.daemon.jobs.ecs_measure import EcsPoint, averaged, measure_ecs
from scancell.daemon.jobs.metrology import MetrologySettings, apply_weather
from scancell.daemon.jobs.runner import JobContext, StepFailed
from scancell.daemon.jobs.scan import ScannerSetup, scan
from scancell.daemon.supervision.supervisor import DeviceSupervisor, hold_for_job
from scancell.devices.base import Robot, Tracker
from scancell.devices.simulator import BallPlacer, Simulator
from scancell.model.ball_layout import ball_layout
from scancell.model.cell_geometry import REAR_SMR, CellGeometry
from scancell.protocols.commands import CommandError
from scancell.protocols.plan import DEFAULT_J6_ANGLES_DEG


class OperatorPlacer:
    """A real cell: the operator places the ball and confirms with its rough position."""

    def __init__(self, ctx: JobContext) -> None:
        self.ctx = ctx

    async def place(self, i: int, target_mcs: np.ndarray) -> np.ndarray:
        reply = await self.ctx.wait_confirm(
            f"place the calibration ball at position {i + 1} (about {target_mcs.round(0).tolist()} "
            f"mm in the scanner frame) and confirm with cmd/job/confirm {{approx_world_mm}}")
        if "approx_world_mm" not in reply:
            raise CommandError("invalid", "the confirmation needs approx_world_mm for the tracker")
        return np.asarray(reply["approx_world_mm"], float)

    async def remove(self) -> None:
        return None


async def calibrate_hand_eye(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                             simulator: Simulator | None,
                             setup: ScannerSetup | None = None,
                             metrology: MetrologySettings | None = None,
                             geometry: CellGeometry | None = None) -> dict[str, Any]:
    req = ctx.request
    n = int(req.get("balls", 15))
    turns = [float(a) for a in req.get("j6_angles_deg", [*DEFAULT_J6_ANGLES_DEG, 60.0, -60.0])]
    speed = float(req.get("speed", 0.2))
    repeats = int(req.get("tracker_repeats", 10))
    verb = "calibrate_hand_eye"
    devs = measuring_devices(supervisors, req, verb)
    robot_s, tracker_s, proj_s, cam_s = devs.robot, devs.tracker, devs.projector, devs.cameras
    robot: Robot = robot_s.device
    tracker: Tracker = tracker_s.device
    placer: BallPlacer = simulator.ball_placer() if simulator is not None else OperatorPlacer(ctx)
    warm = setup.warn_if_cold(ctx, "the hand-eye calibration") if setup is not None else None
    layout = ball_layout(n, [float(d) for d in req.get("depths_mm", [560.0, 620.0, 680.0])],
                         tuple(req.get("spread_mm", [120.0, 100.0])))

    def sample(kind: str, sid: str, point: np.ndarray, **extra: Any) -> None:
        ctx.bus.publish_json(ctx.bus.keys.hand_eye_sample,
                             {"job_id": ctx.job_id, "kind": kind, "id": sid,
                              "point_mm": [float(v) for v in point], "balls": n, **extra},
                             "scancell.HandEyeSample")

    async with contextlib.AsyncExitStack() as stack:
        await hold_for_job(stack, ctx.job_id, devs.all)
        # Balls first, then the ECS starting from this very pose: the robot does not move
        # between the scans and P1, so its repeatability does not enter between them.
        try:
            weather = await apply_weather(tracker, metrology or MetrologySettings())
        except CommandError as exc:
            raise StepFailed("start", "weather", exc.message) from exc
        if weather.get("warning"):
            ctx.event("running", "weather", weather["warning"])
        q0 = await robot.joints()
        home_smr = (await tracker.measure()).point_mm
        try:
            for i, target in enumerate(layout):
                sid = f"b{i:02d}"
                ctx.event("running", "ball", f"ball {i + 1}/{n}: place, scan, measure", i, n)
                approx = await placer.place(i, target)
                # the ball is matte white: one exposure, whatever the cell's HDR default
                reply = await scan(supervisors, {"station": f"he{i:02d}", "scan_id":
                                                 f"{ctx.job_id}-{sid}", "projector": proj_s.name,
                                                 "cameras": [c.name for c in cam_s],
                                                 "exposures_us": req.get("exposures_us")},
                             hold_locks=False, job_id=ctx.job_id, job_kind=ctx.kind,
                             setup=setup)
                await tracker.find_reflector(approx)
                point, sigma = await averaged(tracker, repeats,
                                              {"job_id": ctx.job_id, "ball": sid})
                sample("ball", sid, point, index=i, scan_id=reply["scan_id"], repeats=repeats,
                       station=reply["station"], sigma_mm=[float(v) for v in sigma])
        finally:
            with contextlib.suppress(Exception):
                await tracker.find_reflector(home_smr)  # back on the scanner's SMR
            await placer.remove()
        ecs = await measure_ecs(
            robot, tracker, q0, turns, speed, repeats, {"job_id": ctx.job_id},
            lambda k, turn, note: ctx.event("running", "ecs", note or f"ECS: J6 {turn:+.1f} deg",
                                            k, len(turns) + 1), metrology=metrology)
        for k, e in enumerate(ecs):
            sample("ecs", f"P{k + 1}", e.point_mm, index=k, j6_deg=e.j6_deg, repeats=repeats,
                   sigma_mm=[float(v) for v in e.sigma_mm])
        cluster: dict[str, Any] = {}
        if geometry is not None and geometry.smr_cluster and req.get("cluster", True):
            cluster = await measure_cluster_turns(ctx, robot, tracker, geometry, q0, ecs[0],
                                                  speed, repeats, metrology, sample)
    return {"balls": n, "ecs_points": len(ecs), "j6_angles_deg": [e.j6_deg for e in ecs[1:]],
            "weather": weather, "settle_s": [e.settle_s for e in ecs], **cluster,
            **({"scanner_warm_up": warm} if warm is not None else {})}


async def measure_cluster_turns(ctx: JobContext, robot: Robot, tracker: Tracker,
                                geometry: CellGeometry, q0: np.ndarray, p1: EcsPoint,
                                speed: float, repeats: int, metrology: MetrologySettings | None,
                                sample: Any) -> dict[str, Any]:
    """The cluster's SMRs at the J6 turns where they face the tracker (each from up to 3
    turns; poses ``j6<turn>``), then those the turns do not show at up to 2 tipped poses
    (``t<k>``) beside >= 3 the turns locate; published as ``cluster`` samples. The robot ends
    back at ``q0`` and the tracker on the rear SMR. The robot model's prediction of each SMR is
    corrected by where the rear SMR really is."""
    rear0 = geometry.smr_positions(q0, None)[REAR_SMR][0]
    offset = p1.point_mm - rear0  # the robot's absolute error and the rail, as the rear sees

    def turned(turn: float) -> np.ndarray:
        q = np.array(q0, float)
        q[5] += np.radians(turn)
        return q

    def facing(turn: float) -> list[str]:
        q = turned(turn)
        if not geometry.robot.within_limits(q):
            return []
        return sorted(set(geometry.facing_smrs(q, None)) - {REAR_SMR})

    turns = cluster_turns(facing, np.arange(-180.0, 180.0, 15.0))
    sightings: dict[str, int] = {}
    for t in turns:
        for name in facing(t):
            sightings[name] = sightings.get(name, 0) + 1
    # SMRs the J6 turns never show (or once): tip the scanner so that they face the tracker
    # beside >= 3 the turns do locate
    known = {n for n, c in sightings.items() if c >= 2} | {REAR_SMR}
    tilts = cluster_tilts(geometry, q0, known, set(geometry.smr_cluster) - known)
    views = [(f"j6{turn:+.0f}", turned(turn), turn) for turn in turns]
    views += [(f"t{k + 1}", q, None) for k, (q, _) in enumerate(tilts)]
    points = 0
    try:
        for k, (pose, q, turn) in enumerate(views):
            ctx.event("running", "cluster", f"SMR cluster: pose {pose} ({k + 1}/{len(views)})",
                      k, len(views))
            await robot.move_joints(q, speed)
            aims = {n: p + offset for n, p in geometry.facing_smrs(q, None).items()
                    if n != REAR_SMR or turn is None}
            shots = await measure_cluster(tracker, geometry, q, None, repeats,
                                          {"job_id": ctx.job_id, "pose": pose}, metrology,
                                          predicted=aims)
            for name, p in shots.points_mm.items():
                sample("cluster", f"{name}@{pose}", p, smr=name, pose=pose, j6_deg=turn,
                       repeats=repeats, sigma_mm=[float(v) for v in shots.sigma_mm[name]])
                points += 1
            for name, why in shots.skipped.items():
                ctx.event("running", "cluster", f"SMR {name} at pose {pose} not measured: {why}")
    finally:
        await robot.move_joints(q0, speed)
        with contextlib.suppress(Exception):
            await tracker.find_reflector(p1.point_mm)
    shown = set(sightings) | {n for _, f in tilts for n in f}
    missing = sorted(set(geometry.smr_cluster) - shown)
    return {"cluster_points": points, "cluster_poses": [v[0] for v in views],
            "cluster_never_facing": missing}
