"""Where the simulated cell's objects stand for a part: the part itself, the robot's rail or
track, the reference nests, the scanner-check bar and the heights a moved tracker may stand at
(world = the tracker's frame at home, z up, the floor at z = -1200 mm).

The car rear (and the small artefacts) use :class:`SimCellConfig`'s defaults: the part 3.3 m in
front of the tracker, the robot on a 3 m straight rail between them.

The ``car_body`` cell (``deploy/cells/sim-car-body.toml`` states the same numbers):

- the body stands on a 350 mm fixture, its middle 3.8 m in front of the tracker (+x), its
  length along world y;
- the robot rides a 500 mm riser on a track round three sides of it: 6 m straight along the near
  side 1.8 m from the body's axis, a curved module of 1.8 m radius round the front, and 6 m
  straight back along the far side (17.65 m in all; curved track modules of 1.5-3 m radius are
  catalogue items of gantry and track makers). The carriage turns with the track, so the robot
  faces the body from both sides;
- the tracker measures from home and from stations round the body, on the floor or on a raised
  platform (head 3.5 m above the floor) for the roof's views; eight reference nests on the
  floor and on stands round the cell tie those stations together.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scancell.model.rail_path import RailModule
from scancell.model.transforms import make_T

#: the car body's underbody middle (part origin) in world, mm: 350 mm above the floor
CAR_BODY_ORIGIN = (3800.0, 0.0, -850.0)
#: the robot base at rail 0 (on a 500 mm riser) and the track's modules from there, heading +y
CAR_BODY_BASE0 = (2000.0, -3300.0, -700.0)
CAR_BODY_TRACK_RADIUS = 1800.0
CAR_BODY_TRACK = (RailModule(6000.0), RailModule(math.pi * CAR_BODY_TRACK_RADIUS, -180.0),
                  RailModule(6000.0))
CAR_BODY_TRACK_MM = sum(m.length_mm for m in CAR_BODY_TRACK)
CAR_BODY_NESTS: dict[str, tuple[float, float, float]] = {
    "N1": (800.0, -3800.0, -1150.0), "N2": (800.0, 3800.0, -1150.0),
    "N3": (6800.0, -3800.0, -1150.0), "N4": (6800.0, 3800.0, -1150.0),
    "N5": (-500.0, -2500.0, 900.0), "N6": (-500.0, 2500.0, 900.0),
    "N7": (8100.0, -2500.0, 900.0), "N8": (8100.0, 2500.0, 900.0),
}
#: the tracker's other stations (its tripod's marks; the "high" ones on a raised platform, the
#: head 3.5 m above the floor, for the roof's and the lids' views): opposite home, off the front
#: and off the rear
CAR_BODY_TRACKER_STATIONS: dict[str, tuple[float, float, float]] = {
    "far": (7600.0, 0.0, 0.0), "front": (3800.0, 7200.0, 0.0), "rear": (3800.0, -7200.0, 0.0),
    "near_high": (0.0, 0.0, 2300.0), "far_high": (7600.0, 0.0, 2300.0),
    "front_high": (3800.0, 7200.0, 2300.0), "rear_high": (3800.0, -7200.0, 2300.0),
}
#: the scanner-check ball bar on a stand behind the body's rear, in reach from rail 0 and
#: across the view from there (``[metrology.scanner_check]`` of sim-car-body.toml)
CAR_BODY_CHECK_BAR = ((3200.0, -4500.0, -450.0), (0.81, 0.58, 0.0))
#: the scanner looks at a point 150 mm in front of the near side's rear door from rail 0 when
#: the cell starts, a little below the tracker's head as at the car rear: the hand-eye job's
#: balls (560-680 mm out) go there, clear of the body, in the tracker's sight under the
#: scanner's housing
CAR_BODY_START_TARGET = (2750.0, -2000.0, -200.0)


def _track_positions(step_mm: float = 400.0) -> tuple[float, ...]:
    n = int(CAR_BODY_TRACK_MM // step_mm)
    return tuple(round(i * CAR_BODY_TRACK_MM / n, 1) for i in range(n + 1))


def cell_layout(part: str | None) -> dict[str, Any]:
    """:class:`SimCellConfig` keyword arguments placing ``part``'s cell ({}: the defaults)."""
    if part != "car_body":
        return {}
    return {"T_world_from_part": make_T(t=list(CAR_BODY_ORIGIN)),
            "T_world_from_rail0": make_T(t=list(CAR_BODY_BASE0)),
            "rail_axis": np.array([0.0, 1.0, 0.0]),
            "rail_path": CAR_BODY_TRACK,
            "rail_limits_mm": (0.0, float(np.ceil(CAR_BODY_TRACK_MM))),
            "rail_positions_mm": _track_positions(),
            "nests_world_mm": dict(CAR_BODY_NESTS),
            "check_bar_world": CAR_BODY_CHECK_BAR,
            "tracker_stations_mm": dict(CAR_BODY_TRACKER_STATIONS),
            "start_target_world": CAR_BODY_START_TARGET}
