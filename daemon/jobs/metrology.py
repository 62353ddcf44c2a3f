"""The cell's metrology defences every measuring job uses (``[metrology]`` in the cell config,
docs/explanation/metrology.md): settle detection before a tracker point, the weather for the tracker's
refraction correction, and the reference nests that control the tracker's drift.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scancell.devices.base import Tracker, TrackerMeasurement
from scancell.model.metrology_settings import MetrologySettings
from scancell.protocols import tracker_line
from scancell.protocols.commands import CommandError

__all__ = ["MetrologySettings", "NotSettled", "Settled", "apply_weather", "settle"]


# ------------------------------------------------------------------------------ weather
async def apply_weather(tracker: Tracker, settings: MetrologySettings) -> dict[str, Any]:
    """Tell the tracker the air for its refraction correction. Returns what was applied
    (``source``, the values) or, when the cell states no weather, a ``warning``; a value out of
    range is a CommandError naming it and its range."""
    if settings.weather is None:
        return {"source": None, "warning": "no weather in [metrology]: the tracker corrects for "
                                           "whatever air it was last told (1 ppm per °C wrong)"}
    if settings.weather == "config":
        values = (settings.air_temperature_c, settings.air_pressure_hpa, settings.humidity_pct)
        source = "config"
    else:
        st = await tracker.status()
        values = (st.temperature_c, st.pressure_hpa, st.humidity_pct)
        source = f"{tracker.name} weather station"
        if any(v is None for v in values):
            raise CommandError("device_fault", f"{source} reports no weather {values}: set "
                                               f"[metrology] weather = \"config\" and the values")
    problem = tracker_line.environment_problem(*(float(v) for v in values))  # type: ignore[arg-type]
    if problem:
        raise CommandError("out_of_range", f"weather from {source}: {problem}")
    t, p, h = (float(v) for v in values)  # type: ignore[arg-type]
    await tracker.set_environment(t, p, h)
    return {"source": source, "air_temperature_c": t, "air_pressure_hpa": p, "humidity_pct": h}


# ------------------------------------------------------------------------------ settling
@dataclass(frozen=True)
class Settled:
    """The tracker's readings agreed: after ``settle_s`` (the tracker's clock) and
    ``samples`` readings whose last window spread ``spread_mm`` about their mean."""

    settle_s: float
    samples: int
    spread_mm: float
    last: TrackerMeasurement


class NotSettled(CommandError):
    def __init__(self, message: str) -> None:
        super().__init__("not_settled", message)


def _seconds(a: TrackerMeasurement, b: TrackerMeasurement) -> float:
    if a.device_stamp_ns is not None and b.device_stamp_ns is not None:
        return (b.device_stamp_ns - a.device_stamp_ns) / 1e9
    return (b.stamp_ns - a.stamp_ns) / 1e9


async def settle(tracker: Tracker, settings: MetrologySettings, meta: dict[str, Any]
                 ) -> Settled:
    """Sample the locked SMR until ``settle_window`` consecutive readings lie within
    ``settle_tolerance_mm`` (plus twice their stated 1-sigma) of their mean; never a fixed
    sleep. NotSettled after
    ``settle_timeout_s`` of the tracker's clock. Every reading goes on the bus with ``meta``."""
    shots: list[TrackerMeasurement] = []
    spread = float("inf")
    while True:
        shots.append(await tracker.measure_published({**meta, "settle": len(shots)}))
        window = shots[-settings.settle_window:]
        if len(window) == settings.settle_window:
            pts = np.array([m.point_mm for m in window])
            spread = float(np.linalg.norm(pts - pts.mean(axis=0), axis=1).max())
            # the tracker's own noise is no motion: allow twice its stated 1-sigma on top
            noise = 2.0 * float(np.mean([np.linalg.norm(m.sigma_mm) for m in window]))
            if spread <= settings.settle_tolerance_mm + noise:
                return Settled(_seconds(shots[0], window[0]), len(shots), spread, shots[-1])
        if _seconds(shots[0], shots[-1]) > settings.settle_timeout_s:
            raise NotSettled(f"the tracker's readings did not settle within "
                             f"{settings.settle_timeout_s:g} s: the last "
                             f"{settings.settle_window} spread {spread:.3f} mm > "
                             f"{settings.settle_tolerance_mm:g} mm (is the cell vibrating?)")
