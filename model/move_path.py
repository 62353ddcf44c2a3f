"""The poses a move sweeps through between two stations, not only where it ends.

The scan job moves the arm and the rail together (:meth:`Station.move_to`): a joint move, its
joints starting and ending together (linear in joint space, as a FANUC J move), takes
``RobotModel.travel_time``; the rail starts with it and runs at ``rail_speed_mm_s``. Whichever
ends first waits for the other. So the scanner's path between two stations that each stand clear
of the part may still pass through it: a wrist turned half round on the way from a side view to
an underbody view, or an arm that reaches its next pose while the rail is still carrying it round
a curved track.

Samples are spaced so that no optical centre moves more than ``step_mm`` between two of them
(a bound from each joint's turn times its lever, ``RobotModel.joint_levers_mm``, and the rail's
travel and curvature times the arm's lever, :func:`lever_mm`). A path
whose samples all stand ``c`` clear of an obstacle cannot come nearer than ``c - step_mm / 2``
between them: the planner samples every ``clearance_mm / 2`` so the path keeps ``3/4`` of the
clearance.
"""

from __future__ import annotations

import numpy as np
from scancell.model.cell_geometry import CellGeometry


def lever_mm(g: CellGeometry) -> float:
    """A bound (mm) on how far an optical centre stands from any joint's axis: the arm's reach,
    its shoulder offset and the scanner's optical centres from the flange. A joint turn of
    ``dq`` rad moves an optical centre at most ``dq * lever_mm``."""
    centres = g.optical_centres_in_flange()
    return float(g.robot.reach_mm + abs(g.robot.dh[0].a) + abs(g.robot.dh[5].d)
                 + np.linalg.norm(centres, axis=1).max())


def move_times(g: CellGeometry, q_from: np.ndarray, rail_from: float | None,
               q_to: np.ndarray, rail_to: float | None, speed: float) -> tuple[float, float]:
    """(arm, rail) seconds of a move: the joint move at ``speed`` x the joints' maximum speeds,
    the rail at the cell's ``rail_speed_mm_s``."""
    arm = g.robot.travel_time(q_from, q_to, speed)
    rail = abs((rail_to or 0.0) - (rail_from or 0.0)) / g.rail_speed_mm_s
    return arm, rail


def move_flange_poses(g: CellGeometry, q_from: np.ndarray, rail_from: float | None,
                      q_to: np.ndarray, rail_to: float | None, speed: float,
                      step_mm: float) -> np.ndarray:
    """(n, 4, 4) the flange's poses in ``world`` (mm) along a move from joints ``q_from`` (rad)
    at rail ``rail_from`` (mm) to ``q_to`` at ``rail_to``, both ends included, no optical centre
    travelling more than ``step_mm`` between two of them."""
    q0, q1 = np.asarray(q_from, float), np.asarray(q_to, float)
    r0, r1 = rail_from or 0.0, rail_to or 0.0
    arm_s, rail_s = move_times(g, q0, rail_from, q1, rail_to, speed)
    tool = float(np.linalg.norm(g.optical_centres_in_flange(), axis=1).max())
    arm_mm = float(np.abs(q1 - q0) @ g.robot.joint_levers_mm(tool))
    turn = g.rail_path.max_turn_per_mm if g.rail_path is not None else 0.0
    rail_mm = abs(r1 - r0) * (1.0 + turn * lever_mm(g))
    # each motion's own grid, at half the step: between two samples each moves <= step / 2
    t = np.union1d(*(np.linspace(0.0, span, max(2, int(np.ceil(2 * mm / step_mm)) + 1))
                     for span, mm in ((arm_s, arm_mm), (rail_s, rail_mm))))
    arm = np.clip(t / arm_s, 0.0, 1.0) if arm_s > 0 else np.ones(len(t))
    rail = np.clip(t / rail_s, 0.0, 1.0) if rail_s > 0 else np.ones(len(t))
    return np.stack([g.base_at(r0 + (r1 - r0) * b)
                     @ g.robot.fk(q0 + (q1 - q0) * a) for a, b in zip(arm, rail, strict=True)])
