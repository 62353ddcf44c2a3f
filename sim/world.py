"""The simulated worlds living in this process, found by name by the in-process sim devices.

A world is one :class:`SimCell` plus what its simulated devices share: a lock serialising
access to the cell from several threads, and the projector's trigger line. The simulator host
(``[simulator]`` in a cell config) registers one; the ``sim_camera`` and ``sim_projector``
drivers look it up by name.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

from scancell.sim.cell import SimCell

#: Called with the pattern index projected during the exposure a trigger pulse starts.
TriggerInput = Callable[[int], None]


class TriggerLine:
    """The projector's trigger output wired to the cameras' trigger inputs.

    Faults can be injected per camera: ``drop`` loses the next N pulses (a loose cable),
    ``double`` makes the next pulse trigger twice (a bouncing line).
    """

    def __init__(self) -> None:
        self._inputs: dict[str, TriggerInput] = {}
        self._drop: dict[str, int] = {}
        self._double: dict[str, int] = {}
        self._lock = threading.Lock()
        self.pulses = 0
        #: called once per pulse (the simulated cell's clock advances by a pattern's period)
        self.on_pulse: Callable[[], None] | None = None

    def connect(self, name: str, callback: TriggerInput) -> None:
        with self._lock:
            self._inputs[name] = callback

    def disconnect(self, name: str) -> None:
        with self._lock:
            self._inputs.pop(name, None)

    def inject(self, camera: str, fault: str, count: int = 1) -> None:
        if fault not in ("drop", "double"):
            raise ValueError(f"unknown trigger fault {fault!r}: use 'drop' or 'double'")
        with self._lock:
            target = self._drop if fault == "drop" else self._double
            target[camera] = target.get(camera, 0) + count

    def pulse(self, pattern: int) -> int:
        """One trigger pulse while ``pattern`` is projected; returns the pulse count."""
        with self._lock:
            self.pulses += 1
            fire: list[TriggerInput] = []
            for name, cb in self._inputs.items():
                if self._drop.get(name, 0) > 0:
                    self._drop[name] -= 1
                    continue
                fire.append(cb)
                if self._double.get(name, 0) > 0:
                    self._double[name] -= 1
                    fire.append(cb)
            count = self.pulses
        if self.on_pulse is not None:
            self.on_pulse()
        for cb in fire:
            cb(pattern)
        return count


@dataclass
class SimWorld:
    name: str
    cell: SimCell
    lock: threading.RLock = field(default_factory=threading.RLock)
    trigger: TriggerLine = field(default_factory=TriggerLine)

    def __post_init__(self) -> None:
        cell = self.cell
        self.trigger.on_pulse = lambda: cell.clock.advance(cell.mech.pattern_s)


_WORLDS: dict[str, SimWorld] = {}
_REGISTRY_LOCK = threading.Lock()


def register(world: SimWorld) -> None:
    with _REGISTRY_LOCK:
        if world.name in _WORLDS:
            raise ValueError(f"a simulated world named {world.name!r} already runs in this process")
        _WORLDS[world.name] = world


def unregister(name: str) -> None:
    with _REGISTRY_LOCK:
        _WORLDS.pop(name, None)


def get_world(name: str) -> SimWorld:
    with _REGISTRY_LOCK:
        try:
            return _WORLDS[name]
        except KeyError:
            raise KeyError(f"no simulated world {name!r} in this process (known: "
                           f"{sorted(_WORLDS) or 'none'}); the cell config needs a "
                           f"[simulator] table with world = {name!r}") from None
