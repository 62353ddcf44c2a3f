"""The simulated world as the hand-eye job's operator: it places the calibration ball where
the scanner sees it and the tracker can reach it, and tells where (roughly, as a person would)."""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
from scancell.model.ball_layout import ball_layout
from scancell.protocols.commands import CommandError


class SimBallPlacer:
    """The simulated world places the ball where the scanner sees it and the tracker can reach
    it, and tells where (approximately, as an operator would)."""

    def __init__(self, world: Any, seed: int = 0) -> None:
        self.world = world
        self.rng = np.random.default_rng([seed, 99])

    async def place(self, i: int, target_mcs: np.ndarray) -> np.ndarray:
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
