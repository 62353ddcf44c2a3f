"""The SMRs of the scanner's cluster the tracker can see at one robot pose, without moving the
robot (issue 19): the tracker is pointed at each in turn (FindReflector at its position
predicted by the robot model and the cluster as drawn), each measured as the mean of
``repeats`` shots. An SMR the tracker cannot lock or measure (occluded by the part or the
housing, turned away) is skipped and named with the reason; the caller decides whether what
is left fixes the scanner's pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scancell.daemon.jobs.ecs_measure import averaged
from scancell.daemon.jobs.metrology import MetrologySettings, settle
from scancell.devices.base import Tracker
from scancell.devices.errors import DeviceFault
from scancell.model.cell_geometry import CellGeometry


@dataclass
class ClusterShots:
    #: SMR -> mean position in the tracker's frame (mm)
    points_mm: dict[str, np.ndarray] = field(default_factory=dict)
    #: SMR -> 1-sigma of the mean per axis (mm)
    sigma_mm: dict[str, np.ndarray] = field(default_factory=dict)
    #: SMR -> why it was not measured
    skipped: dict[str, str] = field(default_factory=dict)
    #: how long the arm took to settle before the first SMR (tracker clock), if checked
    settle_s: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {"smr_tracker_mm": {n: [float(v) for v in p] for n, p in self.points_mm.items()},
                "smr_sigma_mm": {n: [float(v) for v in s] for n, s in self.sigma_mm.items()},
                "smr_skipped": dict(self.skipped)}


async def measure_cluster(tracker: Tracker, geometry: CellGeometry, q_rad: np.ndarray,
                          rail_mm: float | None, repeats: int, meta: dict[str, Any],
                          metrology: MetrologySettings | None = None,
                          T_world_from_tracker: np.ndarray | None = None,
                          predicted: dict[str, np.ndarray] | None = None,
                          skip: frozenset[str] = frozenset()) -> ClusterShots:
    """Measure every SMR facing the tracker at the robot's pose ``q_rad`` (rail at
    ``rail_mm``), or those of ``predicted`` (name -> tracker-frame position, mm) if given;
    ``skip`` names SMRs already measured at this pose. Settles once, on the first SMR locked,
    when ``metrology`` asks for settle detection."""
    aims = (geometry.facing_smrs(q_rad, rail_mm, T_world_from_tracker) if predicted is None
            else predicted)
    shots = ClusterShots()
    for name, approx in aims.items():
        if name in skip:
            continue
        smr_meta = {**meta, "smr": name}
        try:
            await tracker.find_reflector(np.asarray(approx, float))
            if shots.settle_s is None and metrology is not None and metrology.settle:
                shots.settle_s = (await settle(tracker, metrology, smr_meta)).settle_s
            p, s = await averaged(tracker, repeats, smr_meta)
        except DeviceFault as exc:  # beam broken, no reflector there; a lost link is no skip
            shots.skipped[name] = str(exc) or type(exc).__name__
            continue
        if np.linalg.norm(p - approx) > 50.0:
            shots.skipped[name] = (f"locked {np.linalg.norm(p - approx):.0f} mm from where it "
                                   f"should be: another reflector")
            continue
        shots.points_mm[name], shots.sigma_mm[name] = p, s
    return shots
