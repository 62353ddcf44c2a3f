"""The poses a move sweeps through (``model.move_path``): no optical centre travels more than
the step between two samples, whatever the joints and the curved rail do. The planner's
clearance along a move, and the simulator's collision sweep, rest on this bound."""

from __future__ import annotations

import numpy as np
import pytest
from scancell.model.cell_geometry import CellGeometry
from scancell.model.move_path import move_flange_poses
from scancell.sim.cell import SimCell, SimCellConfig


@pytest.fixture(scope="module")
def car_body_cell() -> CellGeometry:
    """The car body's cell: its rail runs round the body's corners."""
    return CellGeometry.from_table(
        SimCell(SimCellConfig.for_part("car_body", camera_scale=8)).planner_table())


def _tracks(g: CellGeometry, Ts: np.ndarray) -> np.ndarray:
    """(n, 3, 3) the optical centres (world, mm) at each of ``n`` flange poses."""
    local = g.optical_centres_in_flange()
    return np.einsum("nij,kj->nki", Ts[:, :3, :3], local) + Ts[:, None, :3, 3]


@pytest.mark.unit
def test_a_joint_turn_moves_no_optical_centre_further_than_its_lever(car_body_cell):
    g = car_body_cell
    tool = float(np.linalg.norm(g.optical_centres_in_flange(), axis=1).max())
    levers = g.robot.joint_levers_mm(tool)
    assert np.all(np.diff(levers) <= 0) and levers[5] == pytest.approx(tool)
    rng = np.random.default_rng(7)
    lo, hi = g.robot.limits_rad.T
    dq = 1e-3
    worst = np.zeros(6)
    for _ in range(300):
        q = rng.uniform(lo, hi)
        at = _tracks(g, g.robot.fk(q)[None])[0]
        for i in range(6):
            turned = q.copy()
            turned[i] += dq
            moved = np.linalg.norm(_tracks(g, g.robot.fk(turned)[None])[0] - at, axis=1).max()
            worst[i] = max(worst[i], moved / dq)
    assert np.all(worst <= levers * (1 + 1e-6)), (worst, levers)
    # and the wrist's bounds are the wrist's, not the whole arm's: they cut a wrist turn's
    # samples by the ratio to the arm's reach
    assert levers[3] < 0.2 * levers[0] and worst[3] > 0.5 * levers[3]


@pytest.mark.unit
def test_every_point_of_a_move_lies_within_half_a_step_of_a_sample(car_body_cell):
    """Sampled 8 times finer, each optical centre's path stays within step/2 of the coarse
    samples of its own track: an obstacle ``c`` from every sample is ``c - step/2`` from the
    path. Wrist turns, whole-arm moves and rail runs round the track's corners."""
    from scipy.spatial import cKDTree

    g = car_body_cell
    rng = np.random.default_rng(3)
    lo, hi = g.robot.limits_rad.T
    rails = np.asarray(g.rail_positions_mm, float)
    step = 50.0
    for k in range(12):
        q0 = rng.uniform(lo, hi)
        q1 = q0.copy()
        if k % 3 == 0:  # a wrist turn
            q1[3:] = rng.uniform(lo[3:], hi[3:])
        else:
            q1 = rng.uniform(lo, hi)
        r0, r1 = (rng.choice(rails, 2) if k % 2 else (rails[0], rails[0]))
        coarse = _tracks(g, move_flange_poses(g, q0, r0, q1, r1, 0.5, step))
        fine = _tracks(g, move_flange_poses(g, q0, r0, q1, r1, 0.5, step / 8))
        assert len(fine) > len(coarse) >= 2
        for j in range(3):
            gap = cKDTree(coarse[:, j]).query(fine[:, j])[0]
            assert gap.max() <= step / 2 + 1e-6, (k, j, gap.max())
