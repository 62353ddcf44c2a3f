"""What measuring a station takes (the devices, the plan's motion and ECS settings, the
metrology defences in force): shared by the scan job, its scanner checks and the acceptance
job's stations."""

from __future__ import annotations

from dataclasses import dataclass

from scancell.daemon.jobs.metrology import MetrologySettings
from scancell.daemon.jobs.nests import DriftControl
from scancell.daemon.jobs.scan import ScannerSetup
from scancell.devices.base import Axis, Robot, Tracker
from scancell.model.cell_geometry import CellGeometry


@dataclass(frozen=True)
class Station:
    """What measuring a station takes: the devices and the plan's motion and ECS settings."""

    robot: Robot
    tracker: Tracker
    axis: Axis | None
    projector: str
    cameras: list[str]
    speed: float
    repeats: int
    turns: list[float]
    setup: ScannerSetup | None
    #: settle detection before each tracker point (None: measure at once)
    metrology: MetrologySettings | None = None
    #: the tracker's location by the reference nests (None: the tracker's frame is ``world``)
    drift: DriftControl | None = None
    #: whether the tracker was told the weather (the refraction's uncertainty)
    weather_applied: bool = False
    #: the cell's geometry: where the scanner's SMRs are (the cluster method aims by it)
    geometry: CellGeometry | None = None
    #: the ECS method of stations that do not name one ("j6" or "cluster")
    ecs: str = "j6"
    #: cluster stations also take the J6 turns after the scan, to compare the two methods
    compare_ecs: bool = False
