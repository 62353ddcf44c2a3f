"""The embedded simulated cell as the daemon, the config and the workers see it: a
:class:`Simulator` reached by name (``SIMULATOR``), never by import, as drivers are reached
through ``devices/registry.py``. Runtime code therefore never imports ``scancell.sim``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

#: ``module:Class`` of the simulator a config's ``[simulator]`` table starts.
SIMULATOR = "scancell.sim.host:SimHost"


class BallPlacer(Protocol):
    """Who puts the hand-eye calibration ball in front of the scanner."""

    async def place(self, i: int, target_mcs: np.ndarray) -> np.ndarray:
        """Place ball ``i`` near ``target_mcs`` (scanner frame, mm); return its rough position
        in ``world`` (mm), for pointing the tracker."""
        ...

    async def remove(self) -> None: ...


class ArtefactPlacer(Protocol):
    """Who puts the VDI/VDE 2634 artefacts in the scanner's measuring volume."""

    async def place(self, kind: str, centre_mcs: np.ndarray, direction_mcs: np.ndarray) -> None:
        """Place artefact ``kind`` (sphere, ballbar, plane) at ``centre_mcs`` (scanner frame,
        mm); ``direction_mcs``: a ball bar's axis or a plane's normal."""
        ...

    async def place_world(self, kind: str, centre_world: np.ndarray,
                          direction_world: np.ndarray) -> None:
        """Place a ball bar in the cell (tracker frame, mm), for a multiple-view test."""
        ...

    async def remove(self) -> None: ...


class TrackerMover(Protocol):
    """Who sets the tracker up at another station of a plan."""

    async def move(self, name: str, T_world_from_base: np.ndarray) -> None:
        """Set the tracker up at station ``name``, roughly at ``T_world_from_base`` (its head
        at the translation, world, mm); returns once it stands there, warm and levelled."""
        ...


class ScannerClock(Protocol):
    """How long the scanner has been switched on, and time passing while the cell waits for
    its warm-up."""

    def powered_s(self) -> float:
        """Seconds since the scanner was switched on."""
        ...

    async def wait(self, seconds: float) -> None:
        """Let ``seconds`` pass with the cell standing still."""
        ...


class Simulator(Protocol):
    """A simulated cell started from a ``[simulator]`` table; its servers speak the real
    devices' protocols on sockets, so the daemon's drivers cannot tell it from hardware."""

    def __init__(self, options: dict[str, Any]) -> None: ...

    @staticmethod
    def check_options(options: dict[str, Any]) -> str | None:
        """The first problem with a ``[simulator]`` table, as ``"key: message"``, or None."""
        ...

    @staticmethod
    def planner_table(options: dict[str, Any]) -> dict[str, Any]:
        """The simulated cell's geometry as a ``[planner]`` table (what a real cell states)."""
        ...

    @staticmethod
    def truth(options: dict[str, Any]) -> Callable[[np.ndarray], np.ndarray]:
        """The true-distance function (world points, mm -> mm) of the simulated part."""
        ...

    def start(self, timeout_s: float = 60.0) -> None: ...

    def stop(self) -> None: ...

    def ball_placer(self) -> BallPlacer:
        """The simulated world placing the calibration ball, as an operator would."""
        ...

    def artefact_placer(self) -> ArtefactPlacer:
        """The simulated world placing the acceptance test's artefacts."""
        ...

    def scanner_clock(self) -> ScannerClock:
        """The simulated scanner's time since power-on (sim time), which passes when waited."""
        ...

    def tracker_mover(self) -> TrackerMover:
        """The simulated world setting the tracker up at a plan's other stations."""
        ...


class SimulatorUnavailable(RuntimeError):
    pass


def load_simulator() -> type[Simulator]:
    """Import the simulator class by name; raises SimulatorUnavailable if it cannot be."""
    module, _, attr = SIMULATOR.partition(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise SimulatorUnavailable(f"the simulator {SIMULATOR!r} cannot be loaded: {exc}") from exc
