"""The simulated world as the person who sets the tracker up at a plan's other stations: the
tripod goes roughly where the plan says, levelled, turned by eye (docs/explanation/simulation.md,
"Tracker station moves")."""

from __future__ import annotations

import asyncio
import zlib
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

#: how far a tripod set up by eye lands off the plan's position: 1-sigma x, y, z (mm)
PLACEMENT_SIGMA_MM = (30.0, 30.0, 10.0)
#: how far it is turned off the plan's yaw (1-sigma, deg)
YAW_SIGMA_DEG = 2.0
#: what the tracker's own level leaves of a tilt (1-sigma per horizontal axis, deg)
LEVEL_SIGMA_DEG = 0.01
#: sim time a move takes: carry, set up, warm up and settle (s)
MOVE_S = 600.0


class SimTrackerMover:
    """Moves the simulated tracker to a plan's station with a seeded set-up error, so the job
    has to locate it on the nests; the nests' SMRs are turned towards it."""

    def __init__(self, world: Any, seed: int = 0) -> None:
        self.world = world
        self.seed = seed

    def set_up_pose(self, name: str, T_world_from_base: np.ndarray) -> np.ndarray:
        """Where the tracker really stands when asked to stand at ``T_world_from_base``
        (seeded per station name)."""
        rng = np.random.default_rng([self.seed, 31, zlib.crc32(name.encode())])
        tilt = np.radians(rng.normal(0.0, LEVEL_SIGMA_DEG, 2))
        yaw = np.radians(rng.normal(0.0, YAW_SIGMA_DEG))
        T = np.asarray(T_world_from_base, float).copy()
        T[:3, :3] = Rotation.from_rotvec([tilt[0], tilt[1], yaw]).as_matrix() @ T[:3, :3]
        T[:3, 3] += rng.normal(0.0, 1.0, 3) * np.asarray(PLACEMENT_SIGMA_MM)
        return T

    async def move(self, name: str, T_world_from_base: np.ndarray) -> None:
        def move() -> None:
            with self.world.lock:
                self.world.cell.move_tracker(self.set_up_pose(name, T_world_from_base), MOVE_S)

        await asyncio.to_thread(move)
