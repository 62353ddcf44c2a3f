"""What every job and command does with the cell's devices: find a serving one of a kind, and
stop whatever moves."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from scancell.daemon.supervision.supervisor import DeviceSupervisor
from scancell.devices.base import Axis, Camera, Device, Projector, Robot, Tracker
from scancell.protocols.commands import CommandError

log = logging.getLogger(__name__)


def serving_device(supervisors: dict[str, DeviceSupervisor], name: str | None, kind: type,
                   verb: str) -> DeviceSupervisor:
    """The connected device ``name`` of ``kind`` (``None``: the cell's first of that kind)."""
    what = kind.__name__.lower()
    have = [n for n, s in supervisors.items() if isinstance(s.device, kind)]
    if not have or (name is not None and name not in have):
        raise CommandError("unknown_device", f"{verb}: no {what}"
                                             f"{f' named {name!r}' if name else ''} (have: {have})")
    sup = supervisors[name if name is not None else have[0]]
    if not sup.serving:
        raise CommandError("device_unavailable", f"{verb}: {sup.name} is {sup.status.state}")
    return sup


@dataclass(frozen=True)
class MeasuringDevices:
    """The supervisors a measuring job holds: the robot, the tracker, the projector and the
    two cameras (left first: MCS)."""

    robot: DeviceSupervisor
    tracker: DeviceSupervisor
    projector: DeviceSupervisor
    cameras: list[DeviceSupervisor]

    @property
    def all(self) -> list[DeviceSupervisor]:
        return [self.robot, self.tracker, self.projector, *self.cameras]


def measuring_devices(supervisors: dict[str, DeviceSupervisor], request: dict[str, Any],
                      verb: str) -> MeasuringDevices:
    """The devices a job request names (``robot``, ``tracker``, ``projector``, ``cameras``),
    or the cell's first of each kind and its first two cameras."""
    cams = request.get("cameras") or [s.name for s in supervisors.values()
                                      if isinstance(s.device, Camera)][:2]
    return MeasuringDevices(serving_device(supervisors, request.get("robot"), Robot, verb),
                            serving_device(supervisors, request.get("tracker"), Tracker, verb),
                            serving_device(supervisors, request.get("projector"), Projector, verb),
                            [serving_device(supervisors, c, Camera, verb) for c in cams])


async def stop_motion(devices: Iterable[Device | None], timeout_s: float = 2.0) -> dict[str, str]:
    """Stop every robot and axis among ``devices`` at once, in parallel, even while the calling
    task is being cancelled. Returns ``{name: why}`` of those that could not be reached."""
    movers = [d for d in devices if isinstance(d, Robot | Axis)]
    if not movers:
        return {}
    async def stop(d: Robot | Axis) -> None:
        async with asyncio.timeout(timeout_s):
            await d.stop()

    results = await asyncio.shield(asyncio.gather(*(stop(d) for d in movers),
                                                  return_exceptions=True))
    failed = {d.name: f"{type(r).__name__}: {r}" for d, r in zip(movers, results, strict=True)
              if isinstance(r, BaseException)}
    for name, why in failed.items():
        log.error("device %s: stop failed: %s", name, why)
    return failed
