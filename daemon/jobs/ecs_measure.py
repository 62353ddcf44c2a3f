"""The SMR under J6 rotation: the tracker points an ECS is built from (docs/how-to/scan-a-part.md, steps 2-5).

At the robot's current pose ``q0``: the SMR at J6 = q0[5] (P1), then at each J6 turn (P2, P3, ...),
each point the mean of ``repeats`` tracker shots. If the beam breaks turning one way (the SMR
turns away from the tracker), J6 goes back and the turns are made the other way round; the
angles that were used are returned with the points. J6 always ends back at ``q0``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scancell.daemon.jobs.metrology import MetrologySettings, settle
from scancell.devices.base import Robot, Tracker
from scancell.devices.errors import BeamBroken


@dataclass(frozen=True)
class EcsPoint:
    j6_deg: float  # relative to q0's J6
    point_mm: np.ndarray  # world (tracker) frame
    sigma_mm: np.ndarray  # 1-sigma of the mean
    settle_s: float | None = None  # how long the arm took to settle before it (tracker clock)


async def averaged(tracker: Tracker, repeats: int,
                   meta: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``repeats`` measurements of the locked SMR and its 1-sigma (mm): the tracker's
    noise averages down, the robot's repeatability (one pose) does not need to. Every shot is
    published on ``dev/<tracker>/point`` with ``meta``."""
    ms = [await tracker.measure_published(meta) for _ in range(repeats)]
    return (np.mean([m.point_mm for m in ms], axis=0),
            np.mean([m.sigma_mm for m in ms], axis=0) / np.sqrt(repeats))


async def settled_point(tracker: Tracker, repeats: int, meta: dict[str, Any],
                        metrology: MetrologySettings | None) -> tuple[np.ndarray, np.ndarray,
                                                                      float | None]:
    """:func:`averaged` once the arm has settled (``metrology`` given): the mean, its 1-sigma
    and the settle time (s)."""
    settle_s = None
    if metrology is not None and metrology.settle:
        settle_s = (await settle(tracker, metrology, meta)).settle_s
    p, s = await averaged(tracker, repeats, meta)
    return p, s, settle_s


async def measure_ecs(robot: Robot, tracker: Tracker, q0: np.ndarray, turns_deg: list[float],
                      speed: float, repeats: int, meta: dict[str, Any],
                      progress: Callable[[int, float, str], None],
                      p1: EcsPoint | None = None,
                      metrology: MetrologySettings | None = None) -> list[EcsPoint]:
    """P1 at ``q0`` (or ``p1`` if already measured) and one point per J6 turn, each after the
    arm settled when ``metrology`` is given; ``progress(k, turn, note)`` before each."""
    points: list[EcsPoint] = []
    for attempt, sign in enumerate((1.0, -1.0)):
        try:
            points = [p1] if p1 is not None else []
            for k, turn in enumerate([0.0, *(sign * t for t in turns_deg)]):
                if k == 0 and p1 is not None:
                    continue
                progress(k, turn, "")
                if k:
                    q = np.array(q0, float)
                    q[5] += np.radians(turn)
                    await robot.move_joints(q, speed)
                p, s, settle_s = await settled_point(tracker, repeats,
                                                     {**meta, "ecs": k, "j6_deg": turn},
                                                     metrology)
                points.append(EcsPoint(turn, p, s, settle_s))
            break
        except BeamBroken as exc:
            await robot.move_joints(q0, speed)
            if attempt:
                raise
            progress(0, 0.0, f"beam lost turning J6 that way ({exc}); turning the other way")
            if points:
                await tracker.find_reflector(points[0].point_mm)
    await robot.move_joints(q0, speed)
    return points
