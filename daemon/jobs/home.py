"""``cmd/home``: a job that brings the robot to its home pose and homes the external axis."""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from scancell.daemon.jobs.devices import serving_device, stop_motion
from scancell.daemon.jobs.runner import JobContext
from scancell.daemon.supervision.supervisor import DeviceSupervisor, hold_for_job
from scancell.devices.base import Axis, Robot
from scancell.protocols.commands import CommandError


async def home(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
               home_joints_deg: tuple[float, ...] | None) -> dict[str, Any]:
    q_deg = ctx.request.get("joints_deg", home_joints_deg)
    if q_deg is None:
        raise CommandError("invalid", "home: no joints_deg given and no [daemon] "
                                      "home_joints_deg in the cell config")
    speed = float(ctx.request.get("speed", 0.2))
    robot_s = serving_device(supervisors, None, Robot, "home")
    axes = [s for s in supervisors.values() if isinstance(s.device, Axis) and s.serving]
    robot: Robot = robot_s.device
    robot.check_joints(np.radians(q_deg))
    async with contextlib.AsyncExitStack() as stack:
        await hold_for_job(stack, ctx.job_id, [robot_s, *axes])
        try:
            ctx.event("running", "move", f"robot to home {list(q_deg)} deg")
            await robot.move_joints(np.radians(q_deg), speed)
            for a in axes:
                ctx.event("running", "axis", f"homing {a.name}")
                await a.device.home()
        except BaseException:
            await stop_motion([robot, *(a.device for a in axes)])
            raise
    return {"joints_deg": [float(v) for v in q_deg], "axes_homed": [a.name for a in axes]}
