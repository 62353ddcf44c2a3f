"""The simulated world as the acceptance test's operator: it takes the part out of the
measuring volume and puts each VDI/VDE 2634 artefact where the job asks, in the scanner's
frame, off by a few millimetres and degrees as a person would place it."""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
from scancell.model.transforms import make_T
from scancell.sim import parts
from scancell.sim.scene import SceneObject
from scipy.spatial.transform import Rotation

PLACEMENT_MM, PLACEMENT_DEG = 3.0, 1.5  # 1 sigma of a hand placement


def artefact_pose_mcs(kind: str, centre: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """T_mcs_from_artefact: the artefact's front (-x) towards the scanner (MCS origin); a ball
    bar's axis (y) along ``direction``; a plane's normal along ``direction``, long side along
    MCS x."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    towards = -np.asarray(centre, float) / np.linalg.norm(centre)  # from the artefact to the scanner
    if kind == "plane":
        x = -d
        y = np.array([1.0, 0.0, 0.0]) - x[0] * x
    else:
        y = d if kind == "ballbar" else np.array([1.0, 0.0, 0.0])
        x = -(towards - (towards @ y) * y)
    x /= np.linalg.norm(x)
    y = y - (y @ x) * x
    y /= np.linalg.norm(y)
    return make_T(np.stack([x, y, np.cross(x, y)], axis=1), centre)


class SimArtefactPlacer:
    def __init__(self, world: Any, seed: int = 0) -> None:
        self.world = world
        self.rng = np.random.default_rng([seed, 2634])
        self._part: SceneObject | None = None

    async def place(self, kind: str, centre_mcs: np.ndarray, direction_mcs: np.ndarray) -> None:
        await asyncio.to_thread(self._put, kind, artefact_pose_mcs(kind, centre_mcs,
                                                                   direction_mcs), True)

    async def place_world(self, kind: str, centre_world: np.ndarray,
                          direction_world: np.ndarray) -> None:
        """A ball bar (axis along ``direction_world``) facing -x of the world, where the robot
        looks at the part from."""
        y = np.asarray(direction_world, float) / np.linalg.norm(direction_world)
        x = np.array([1.0, 0.0, 0.0]) - y[0] * y
        x /= np.linalg.norm(x)
        T = make_T(np.stack([x, y, np.cross(x, y)], axis=1), centre_world)
        await asyncio.to_thread(self._put, kind, T, False)

    def _put(self, kind: str, T: np.ndarray, in_mcs: bool) -> None:
        with self.world.lock:
            cell = self.world.cell
            if self._part is None and cell.cfg.part:
                self._part = cell.scene.get(cell.cfg.part)
                cell.remove_object(cell.cfg.part)  # a free measuring volume
            for name in parts.ARTEFACTS:
                if any(o.name == name for o in cell.scene.objects):
                    cell.remove_object(name)
            jitter = make_T(Rotation.from_rotvec(np.radians(self.rng.normal(
                0, PLACEMENT_DEG, 3))).as_matrix(), self.rng.normal(0, PLACEMENT_MM, 3))
            T_world = (cell.T_world_from_mcs() @ T if in_mcs else T) @ jitter
            cell.add_object(SceneObject(kind, parts.ARTEFACTS[kind](), T_world, 0.6))

    async def remove(self) -> None:
        def take() -> None:
            with self.world.lock:
                cell = self.world.cell
                for name in parts.ARTEFACTS:
                    if any(o.name == name for o in cell.scene.objects):
                        cell.remove_object(name)
                if self._part is not None:
                    cell.add_object(self._part)
                    self._part = None

        await asyncio.to_thread(take)
