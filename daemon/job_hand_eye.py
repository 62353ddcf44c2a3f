"""``cmd/job/calibrate_hand_eye``: the observations for the paper's hand-eye calibration.

At the current robot pose: the scanner's SMR measured by the tracker at J6 = q6 and at the
J6 turns (the ECS); then, for each of N positions of the calibration ball spread over the
scanner's field and depth, a coupled scan (``cmd/scan`` frames) and a tracker measurement of
the ball. Every observation goes out on ``calib/hand_eye/sample``; ``scancell worker
calibrate`` turns them into ``T_ecs_from_mcs``. On the simulated cell the world places the
ball (as an operator would); on a real cell the job waits for ``cmd/job/confirm`` each time.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

import numpy as np
from scancell.daemon.ecs_measure import averaged, measure_ecs
from scancell.daemon.jobs import JobContext
from scancell.daemon.scan import scan, serving_device
from scancell.daemon.supervisor import DeviceSupervisor, hold_for_job
from scancell.devices.base import Camera, Projector, Robot, Tracker
from scancell.protocols.commands import CommandError
from scancell.protocols.plan import DEFAULT_J6_ANGLES_DEG


def ball_layout(n: int, depths_mm: list[float], spread_mm: tuple[float, float],
                baseline_mm: float = 300.0, crossing_mm: float = 676.0) -> np.ndarray:
    """``n`` ball centres in MCS (mm) spread over the common field and the depth range: the
    centre, the corners and the edge midpoints of a ``spread`` rectangle centred on the bisector
    of the two optical axes (which cross ``crossing_mm`` in front of the left camera; the right
    camera is ``baseline_mm`` along +x), each at the next depth in turn. Any three consecutive
    balls span a plane, so a job that loses a ball or two still has a usable geometry."""
    sx, sy = spread_mm
    pattern = [(0, 0), (1, 1), (-1, -1), (1, -1), (-1, 1), (1, 0), (-1, 0), (0, 1), (0, -1)]
    out = []
    for i in range(n):
        px, py = pattern[i % len(pattern)]
        d = depths_mm[(i + i // len(pattern)) % len(depths_mm)]
        out.append([baseline_mm / 2 * (1 - d / crossing_mm) + px * sx / 2, py * sy / 2, d])
    return np.asarray(out, float)


class SimBallPlacer:
    """The simulated world places the ball where the scanner sees it and the tracker can reach
    it, and tells where (approximately, as an operator would)."""

    def __init__(self, world: Any, seed: int = 0) -> None:
        self.world = world
        self.rng = np.random.default_rng([seed, 99])

    async def place(self, ctx: JobContext, i: int, target_mcs: np.ndarray) -> np.ndarray:
        def put() -> np.ndarray:
            with self.world.lock:
                cell = self.world.cell
                T = cell.T_world_from_mcs()
                centre = ball_layout(1, [float(target_mcs[2])], (0.0, 0.0))[0]
                for shrink in (1.0, 0.7, 0.4, 0.0):  # out of view or beam blocked: nearer the axis
                    m = centre + shrink * (target_mcs - centre)
                    if not self._in_both_images(cell, m):
                        continue
                    p = T[:3, :3] @ m + T[:3, 3]
                    cell.place_ball(p)
                    try:
                        cell.beam_check("ball")
                        return p + self.rng.normal(0, 3.0, 3)
                    except Exception:
                        continue
                raise CommandError("device_fault", f"ball position {i}: no place in view of both "
                                                   f"the scanner and the tracker")

        return await asyncio.to_thread(put)

    @staticmethod
    def _in_both_images(cell: Any, centre_mcs: np.ndarray, radius: float = 25.0) -> bool:
        rig = cell.rig
        pts = centre_mcs + radius * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0.0]])
        T_right_from_mcs = np.linalg.inv(rig.T_mcs_from_right)
        for cam, p in ((rig.left, pts), (rig.right, pts @ T_right_from_mcs[:3, :3].T
                                         + T_right_from_mcs[:3, 3])):
            uv = cam.project(p)
            if np.any(uv < 5) or np.any(uv[:, 0] > cam.width - 5) or np.any(uv[:, 1] > cam.height - 5):
                return False
        return True

    async def remove(self) -> None:
        def take() -> None:
            with self.world.lock:
                self.world.cell.remove_ball()
        await asyncio.to_thread(take)


class OperatorPlacer:
    """A real cell: the operator places the ball and confirms with its rough position."""

    async def place(self, ctx: JobContext, i: int, target_mcs: np.ndarray) -> np.ndarray:
        reply = await ctx.wait_confirm(
            f"place the calibration ball at position {i + 1} (about {target_mcs.round(0).tolist()} "
            f"mm in the scanner frame) and confirm with cmd/job/confirm {{approx_world_mm}}")
        if "approx_world_mm" not in reply:
            raise CommandError("invalid", "the confirmation needs approx_world_mm for the tracker")
        return np.asarray(reply["approx_world_mm"], float)

    async def remove(self) -> None:
        return None


async def calibrate_hand_eye(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                             simulator: Any) -> dict[str, Any]:
    req = ctx.request
    n = int(req.get("balls", 15))
    turns = [float(a) for a in req.get("j6_angles_deg", [*DEFAULT_J6_ANGLES_DEG, 60.0, -60.0])]
    speed = float(req.get("speed", 0.2))
    repeats = int(req.get("tracker_repeats", 10))
    verb = "calibrate_hand_eye"
    robot_s = serving_device(supervisors, req.get("robot"), Robot, verb)
    tracker_s = serving_device(supervisors, req.get("tracker"), Tracker, verb)
    proj_s = serving_device(supervisors, req.get("projector"), Projector, verb)
    cams = req.get("cameras") or [s.name for s in supervisors.values()
                                  if isinstance(s.device, Camera)][:2]
    cam_s = [serving_device(supervisors, c, Camera, verb) for c in cams]
    robot: Robot = robot_s.device
    tracker: Tracker = tracker_s.device
    placer = (SimBallPlacer(simulator.world) if simulator is not None and simulator.world
              else OperatorPlacer())
    layout = ball_layout(n, [float(d) for d in req.get("depths_mm", [560.0, 620.0, 680.0])],
                         tuple(req.get("spread_mm", [120.0, 100.0])))

    def sample(kind: str, sid: str, point: np.ndarray, **extra: Any) -> None:
        ctx.bus.publish_json(ctx.bus.keys.hand_eye + "/sample",
                             {"job_id": ctx.job_id, "kind": kind, "id": sid,
                              "point_mm": [float(v) for v in point], "balls": n, **extra},
                             "scancell.HandEyeSample")

    async with contextlib.AsyncExitStack() as stack:
        await hold_for_job(stack, ctx.job_id, [robot_s, tracker_s, proj_s, *cam_s])
        # Balls first, then the ECS starting from this very pose: the robot does not move
        # between the scans and P1, so its repeatability does not enter between them.
        q0 = await robot.joints()
        home_smr = (await tracker.measure()).point_mm
        try:
            for i, target in enumerate(layout):
                sid = f"b{i:02d}"
                ctx.event("running", "ball", f"ball {i + 1}/{n}: place, scan, measure", i, n)
                approx = await placer.place(ctx, i, target)
                reply = await scan(supervisors, {"station": f"he{i:02d}", "scan_id":
                                                 f"{ctx.job_id}-{sid}", "projector": proj_s.name,
                                                 "cameras": [c.name for c in cam_s]},
                             hold_locks=False)
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
                                            k, len(turns) + 1))
        for k, e in enumerate(ecs):
            sample("ecs", f"P{k + 1}", e.point_mm, index=k, j6_deg=e.j6_deg, repeats=repeats,
                   sigma_mm=[float(v) for v in e.sigma_mm])
    return {"balls": n, "ecs_points": len(ecs), "j6_angles_deg": [e.j6_deg for e in ecs[1:]]}
