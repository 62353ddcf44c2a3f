"""What measuring a station takes (the devices, the plan's motion and ECS settings, the
metrology defences in force): shared by the scan job, its scanner checks and the acceptance
job's stations."""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scancell.daemon.jobs.metrology import MetrologySettings
from scancell.daemon.jobs.nests import DriftControl
from scancell.daemon.jobs.scan import ScannerSetup
from scancell.devices.base import Axis, Robot, Tracker
from scancell.devices.errors import DeviceFault
from scancell.model.cell_geometry import REAR_SMR, CellGeometry
from scancell.protocols.plan import Via


@dataclass(frozen=True)
class Station:
    """What measuring a station takes: the devices and the plan's motion and ECS settings."""

    robot: Robot
    tracker: Tracker
    axis: Axis | None
    projector: str
    cameras: list[str]
    speed: float
    repeats: int
    turns: list[float]
    setup: ScannerSetup | None
    #: settle detection before each tracker point (None: measure at once)
    metrology: MetrologySettings | None = None
    #: the tracker's location by the reference nests (None: the tracker's frame is ``world``)
    drift: DriftControl | None = None
    #: whether the tracker was told the weather (the refraction's uncertainty)
    weather_applied: bool = False
    #: the cell's geometry: where the scanner's SMRs are (the cluster method aims by it)
    geometry: CellGeometry | None = None
    #: the ECS method of stations that do not name one ("j6" or "cluster")
    ecs: str = "j6"
    #: cluster stations also take the J6 turns after the scan, to compare the two methods
    compare_ecs: bool = False

    async def move_to(self, q_rad: np.ndarray, axis_mm: float | None = None) -> None:
        """The arm to joints ``q_rad`` (at the plan's speed) and, where the cell has a rail and
        ``axis_mm`` is given, the rail to it at the same time: the rail is the arm's seventh
        axis, and two moves one after the other cost their sum. Returns once both stand; a
        failure of either is raised once the other has ended."""
        moves = [self.robot.move_joints(q_rad, self.speed)]
        if axis_mm is not None and self.axis is not None:
            moves.append(self.axis.move_to(axis_mm))
        results = await asyncio.gather(*moves, return_exceptions=True)
        for r in results:
            if isinstance(r, BaseException):
                raise r

    async def move_through(self, vias: Sequence[Via], q_rad: np.ndarray,
                           axis_mm: float | None = None) -> None:
        """To joints ``q_rad`` (rail at ``axis_mm``) through a plan's ``vias`` in order, each a
        move of the arm and the rail together: the way the planner found clear of the part."""
        for v in vias:
            await self.move_to(np.radians(v.joints_deg), v.axis_mm)
        await self.move_to(q_rad, axis_mm)

    async def aim_at_scanner(self, q_rad: np.ndarray, axis_mm: float | None = None) -> None:
        """Lock the tracker on an SMR of the scanner it can see with the arm at ``q_rad`` (rail
        at ``axis_mm``), where the robot model puts it: the SMR whose opening faces the tracker
        best first, any within its acceptance. Without the cell's geometry the tracker keeps
        what it follows. Raises the tracker's DeviceFault (BeamBroken, no reflector) when
        none can be locked."""
        if self.geometry is None:
            return
        T_wt = self.drift.T_world_from_tracker if self.drift is not None else None
        smrs = self.geometry.smr_positions(q_rad, axis_mm, T_wt)
        if not self.geometry.smr_cluster:
            smrs = {REAR_SMR: smrs[REAR_SMR]}
        aims = sorted(smrs.values(), key=lambda pa: pa[1])
        aims = [p for p, angle in aims if angle <= self.geometry.smr_acceptance_deg] or [aims[0][0]]
        for k, aim in enumerate(aims):
            try:
                await self.tracker.find_reflector(np.asarray(aim, float))
                return
            except DeviceFault:
                if k == len(aims) - 1:
                    raise
