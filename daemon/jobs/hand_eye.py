"""``cmd/job/calibrate_hand_eye``: the observations for the paper's hand-eye calibration.

At the current robot pose: the scanner's SMR measured by the tracker at J6 = q6 and at the
J6 turns (the ECS); then, for each of N positions of the calibration ball spread over the
scanner's field and depth, a coupled scan (``cmd/scan`` frames) and a tracker measurement of
the ball. Every observation goes out on ``calib/hand_eye/sample``; ``scancell worker
calibrate`` turns them into ``T_ecs_from_mcs``. On the simulated cell the world places the
ball (as an operator would); on a real cell the job waits for ``cmd/job/confirm`` each time.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from scancell.daemon.jobs.devices import measuring_devices
from scancell.daemon.jobs.ecs_measure import averaged, measure_ecs
from scancell.daemon.jobs.metrology import MetrologySettings, apply_weather
from scancell.daemon.jobs.runner import JobContext, StepFailed
from scancell.daemon.jobs.scan import ScannerSetup, scan
from scancell.daemon.supervision.supervisor import DeviceSupervisor, hold_for_job
from scancell.devices.base import Robot, Tracker
from scancell.devices.simulator import BallPlacer, Simulator
from scancell.model.ball_layout import ball_layout
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
                             metrology: MetrologySettings | None = None) -> dict[str, Any]:
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
    layout = ball_layout(n, [float(d) for d in req.get("depths_mm", [560.0, 620.0, 680.0])],
                         tuple(req.get("spread_mm", [120.0, 100.0])))

    def sample(kind: str, sid: str, point: np.ndarray, **extra: Any) -> None:
        ctx.bus.publish_json(ctx.bus.keys.hand_eye + "/sample",
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
    return {"balls": n, "ecs_points": len(ecs), "j6_angles_deg": [e.j6_deg for e in ecs[1:]],
            "weather": weather, "settle_s": [e.settle_s for e in ecs]}
