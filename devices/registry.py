"""Driver discovery, after python-can's interface registry.

A built-in map from driver name to ``"module:Class"`` is merged with the entry-point group
``scancell.devices``; a driver module is imported only when a config names it.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points

from scancell.devices.base import Device

ENTRY_POINT_GROUP = "scancell.devices"

BUILTIN_DRIVERS: dict[str, str] = {
    "mock_robot": "scancell.devices.mock:MockRobot",
    "mock_tracker": "scancell.devices.mock:MockTracker",
    "mock_camera": "scancell.devices.mock:MockCamera",
    "mock_projector": "scancell.devices.mock:MockProjector",
    "mock_axis": "scancell.devices.mock:MockAxis",
    "simple_message_robot": "scancell.devices.simple_message_robot:SimpleMessageRobot",
    "line_tracker": "scancell.devices.line_tracker:LineTracker",
    "leica_emscon_tracker": "scancell.devices.emscon_tracker:EmsconTracker",
    "canopen_axis": "scancell.devices.canopen_axis:CanopenAxis",
    "opencv_camera": "scancell.devices.opencv_camera:OpenCVCamera",
    "basler_camera": "scancell.devices.basler_camera:BaslerCamera",
    "dlpc350_projector": "scancell.devices.dlpc350_projector:Dlpc350Projector",
    "dlpc900_projector": "scancell.devices.dlpc900_projector:Dlpc900Projector",
    "sim_camera": "scancell.sim.devices:SimCamera",
    "sim_projector": "scancell.sim.devices:SimProjector",
}


class UnknownDriver(KeyError):
    def __str__(self) -> str:
        return str(self.args[0])


def available_drivers() -> dict[str, str]:
    """Every known driver name -> ``"module:Class"`` (entry points may add or override)."""
    drivers = dict(BUILTIN_DRIVERS)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        drivers[ep.name] = ep.value
    return drivers


def load_driver(name: str) -> type[Device]:
    """Import and return the driver class registered as ``name``."""
    drivers = available_drivers()
    if name not in drivers:
        raise UnknownDriver(f"unknown driver {name!r}; known: {', '.join(sorted(drivers))}")
    target = drivers[name]
    module_name, _, attr = target.partition(":")
    try:
        cls = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise UnknownDriver(f"driver {name!r} -> {target!r} cannot be loaded: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Device)):
        raise UnknownDriver(f"driver {name!r} -> {target!r} is not a scancell Device class")
    return cls
