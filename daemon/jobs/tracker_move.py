"""A scan job's tracker station moves: the tracker is set up at another station of the plan
(by the simulated world, or by a person who confirms with ``cmd/job/confirm``), then the
reference nests locate it (``DriftControl.locate``: every set-up in one bundle)."""

from __future__ import annotations

from typing import Any

import numpy as np
from scancell.daemon.jobs.nests import DriftControl
from scancell.daemon.jobs.runner import JobContext
from scancell.model.cell_geometry import REAR_SMR, CellGeometry
from scancell.protocols.commands import CommandError
from scancell.protocols.plan import HOME_TRACKER, Plan


class OperatorTrackerMover:
    """A real cell: a person sets the tracker up, levels it, lets it warm up and confirms."""

    def __init__(self, ctx: JobContext) -> None:
        self.ctx = ctx

    async def move(self, name: str, T_world_from_base: np.ndarray) -> None:
        x, y, z = np.round(T_world_from_base[:3, 3]).tolist()
        yaw = float(np.degrees(np.arctan2(T_world_from_base[1, 0], T_world_from_base[0, 0])))
        await self.ctx.wait_confirm(
            f"set the tracker up at station {name} (head at about {x:.0f}, {y:.0f}, {z:.0f} mm "
            f"in world, turned {yaw:.0f} deg), level it, let it warm up, turn the nests' SMRs "
            f"towards it and confirm with cmd/job/confirm {{}}")


class TrackerMoves:
    """Where the tracker stands during a scan job, and its moves between the plan's tracker
    stations. Each arrival at a station is a new set-up (``t1``, ``t1-2`` on a second visit)."""

    def __init__(self, plan: Plan, drift: DriftControl, mover: Any,
                 geometry: CellGeometry | None) -> None:
        self.plan = plan
        self.drift = drift
        self.mover = mover
        self.geometry = geometry
        self.station = HOME_TRACKER
        self.visits: dict[str, int] = {HOME_TRACKER: 1}
        self.moves: list[dict[str, Any]] = []

    def needed(self) -> bool:
        return any(s.tracker != HOME_TRACKER for s in self.plan.stations)

    def check_possible(self) -> None:
        """Refuse, before any motion, a plan whose tracker moves this cell cannot locate."""
        if not self.needed():
            return
        if not self.drift.enabled:
            raise CommandError("invalid", "the plan moves the tracker, and a move is located on "
                                          "the reference nests: the cell config has none "
                                          "([metrology] nests)")
        if self.geometry is None:
            raise CommandError("invalid", "the plan moves the tracker: the cell's geometry "
                                          "([planner] tracker_world_mm) is needed to find the "
                                          "scanner's SMR from the new station")

    def T_world_from_base(self, name: str) -> np.ndarray:
        """The plan's rough pose of station ``name``'s base (head at the translation)."""
        if name == HOME_TRACKER:
            T = np.eye(4)
            T[:3, 3] = self.geometry.tracker_world_mm
            return T
        return self.plan.trackers[name].T_world_from_base()

    async def move(self, name: str) -> dict[str, Any]:
        """Set the tracker up at ``name`` and locate it on the nests (then
        :meth:`lock_on_scanner`)."""
        T_base = self.T_world_from_base(name)
        await self.mover.move(name, T_base)
        self.visits[name] = self.visits.get(name, 0) + 1
        setup = name if self.visits[name] == 1 else f"{name}-{self.visits[name]}"
        # the readings' frame: the head at tracker_world_mm of it (model/cell_geometry.py)
        T_rough = T_base.copy()
        T_rough[:3, 3] -= T_base[:3, :3] @ np.asarray(self.geometry.tracker_world_mm, float)
        record = await self.drift.locate(setup, T_rough, f"tracker {setup}")
        self.station = name
        self.moves.append({"setup": setup, "station": name, **record["network"]})
        return record

    async def lock_on_scanner(self, q_rad: np.ndarray, rail_mm: float | None) -> None:
        """Point the tracker at the scanner's rear SMR where the robot model puts it at
        ``q_rad`` (through the located set-up) and lock on it."""
        scanner = self.geometry.smr_positions(q_rad, rail_mm,
                                              self.drift.T_world_from_tracker)[REAR_SMR][0]
        await self.drift.tracker.find_reflector(scanner)
