"""What the planner and the scan job need to know of a cell: robot base, scanner mount, SMR,
tracker position, rail (mm, frames as in README "Units and frames"). A cell config states it in ``[planner]``;
the simulated cell supplies its own."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scancell.model.robot_model import RobotModel
from scancell.protocols.plan import DEFAULT_J6_ANGLES_DEG


class GeometryError(ValueError):
    """A ``[planner]`` table is missing a key or has a malformed value."""


@dataclass(frozen=True)
class CellGeometry:
    """What the planner needs to know of the cell (mm, frames as in README "Units and frames")."""

    T_world_from_base: np.ndarray
    T_flange_from_mcs: np.ndarray
    #: Midpoint between the cameras in the flange frame; the flange z axis is the scanner's
    #: viewing direction (the bisector) and x its baseline.
    rig_mid_in_flange: np.ndarray
    smr_in_mcs_mm: np.ndarray
    smr_opening_in_mcs: np.ndarray
    tracker_world_mm: np.ndarray
    smr_acceptance_deg: float = 30.0
    standoff_mm: float = 650.0
    field_mm: tuple[float, float] = (380.0, 280.0)  # usable field at the standoff (x, y)
    depth_mm: tuple[float, float] = (-90.0, 90.0)  # around the standoff
    max_incidence_deg: float = 65.0
    j6_angles_deg: tuple[float, float] = DEFAULT_J6_ANGLES_DEG
    #: An external linear axis carrying the robot (unit vector in world) and the positions (mm)
    #: the planner may use; empty: no axis.
    rail_axis: tuple[float, float, float] | None = None
    rail_positions_mm: tuple[float, ...] = ()
    robot: RobotModel = field(default_factory=RobotModel)

    def base_at(self, rail_mm: float | None) -> np.ndarray:
        T = np.array(self.T_world_from_base, float)
        if rail_mm:
            T[:3, 3] += np.asarray(self.rail_axis or (0.0, 1.0, 0.0), float) * rail_mm
        return T

    @classmethod
    def from_table(cls, t: dict[str, Any]) -> CellGeometry:
        """From a cell config's ``[planner]`` table (matrices as nested lists); raises
        GeometryError naming a missing or malformed key. ``scancell.config`` is its one caller
        for config files."""
        try:
            return cls(np.asarray(t["T_world_from_base"], float),
                       np.asarray(t["T_flange_from_mcs"], float),
                       np.asarray(t["rig_mid_in_flange_mm"], float),
                       np.asarray(t["smr_in_mcs_mm"], float),
                       np.asarray(t.get("smr_opening_in_mcs", [0, 0, -1]), float),
                       np.asarray(t["tracker_world_mm"], float),
                       float(t.get("smr_acceptance_deg", 30.0)),
                       float(t.get("standoff_mm", 650.0)),
                       tuple(t.get("field_mm", (380.0, 280.0))),
                       tuple(t.get("depth_mm", (-90.0, 90.0))),
                       rail_axis=tuple(t["rail_axis"]) if t.get("rail_axis") else None,
                       rail_positions_mm=tuple(float(v) for v in t.get("rail_positions_mm", ())))
        except (TypeError, ValueError) as exc:
            raise GeometryError(str(exc)) from None
        except KeyError as exc:
            raise GeometryError(f"missing key {exc}") from None
