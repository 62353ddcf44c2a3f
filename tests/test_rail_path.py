"""The robot's external axis as a path: a straight rail, and a track with a curved module that
carries the robot round a part, turning it with the track."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from scancell.model.cell_geometry import CellGeometry, GeometryError
from scancell.model.rail_path import RailModule, RailPath
from scancell.model.transforms import make_T
from scancell.sim.cell import SimCell, SimCellConfig

pytestmark = pytest.mark.unit

BASE = make_T(t=[2000.0, -3300.0, -700.0])
R = 1800.0
U_TRACK = RailPath((0.0, 1.0, 0.0), (RailModule(6000.0), RailModule(math.pi * R, -180.0),
                                     RailModule(6000.0)))


def test_a_straight_rail_moves_the_base_along_its_axis_without_turning_it():
    path = RailPath((1.0, 0.0, 0.0))
    for s in (-700.0, 0.0, 1234.5):
        T = path.base_at(BASE, s)
        np.testing.assert_allclose(T[:3, 3], BASE[:3, 3] + [s, 0.0, 0.0])
        np.testing.assert_allclose(T[:3, :3], np.eye(3))


def test_a_curved_module_carries_the_base_round_on_its_radius_and_turns_it():
    start = BASE[:3, 3]
    centre = start + np.array([R, 6000.0, 0.0])  # the arc turns right (clockwise seen from above)
    for f in (0.0, 0.25, 0.5, 1.0):
        T = U_TRACK.base_at(BASE, 6000.0 + f * math.pi * R)
        assert np.linalg.norm(T[:2, 3] - centre[:2]) == pytest.approx(R, abs=1e-6)
        yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]))
        assert yaw == pytest.approx(-180.0 * f, abs=1e-6) or abs(yaw) == pytest.approx(180.0)
    end = U_TRACK.base_at(BASE, U_TRACK.length_mm)
    np.testing.assert_allclose(end[:3, 3], start + np.array([2 * R, 0.0, 0.0]), atol=1e-6)
    np.testing.assert_allclose(end[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-9)
    assert end[2, 3] == BASE[2, 3]  # the track is level
    # past the end the path runs straight on
    np.testing.assert_allclose(U_TRACK.base_at(BASE, U_TRACK.length_mm + 100.0)[:3, 3],
                               end[:3, 3] + [0.0, -100.0, 0.0], atol=1e-6)


def test_the_planner_table_states_the_track_and_a_bad_module_is_named():
    table = {"T_world_from_base": BASE.tolist(), "T_flange_from_mcs": np.eye(4).tolist(),
             "rig_mid_in_flange_mm": [0, 0, 0], "smr_in_mcs_mm": [0, 0, 0],
             "tracker_world_mm": [0, 0, 0], "rail_axis": [0, 1, 0],
             "rail_path": U_TRACK.to_table(), "rail_positions_mm": [0.0, 8827.4]}
    g = CellGeometry.from_table(table)
    np.testing.assert_allclose(g.base_at(U_TRACK.length_mm),
                               U_TRACK.base_at(BASE, U_TRACK.length_mm))
    for bad, says in (([{"length_mm": -5}], "rail_path[0]"),
                      ([{"length_mm": 100, "turn": 90}], "rail_path[0]"),
                      ([{"length_mm": 100}, "straight"], "rail_path[1]")):
        with pytest.raises(GeometryError, match=re.escape(says)):
            CellGeometry.from_table({**table, "rail_path": bad})
    with pytest.raises(GeometryError, match="horizontal"):
        CellGeometry.from_table({**table, "rail_axis": [0, 0, 1]})


def test_the_simulated_robot_stands_where_the_planner_puts_it():
    cell = SimCell(SimCellConfig(part=None, camera_scale=16, T_world_from_rail0=BASE,
                                 rail_path=U_TRACK.modules, rail_limits_mm=(0.0, 18000.0)))
    g = CellGeometry.from_table(cell.planner_table())
    for s in (0.0, 7000.0, 17000.0):
        cell.move_rail(s)
        np.testing.assert_allclose(cell.T_world_from_base, g.base_at(s), atol=1e-9)
    with pytest.raises(ValueError, match="outside"):
        cell.move_rail(-10.0)
