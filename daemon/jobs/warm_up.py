"""``cmd/job/warm_up``: wait for the scanner's warm-up before it is calibrated or measures.

A scanner's baseline and focal lengths grow while it warms after power-on (tens of ppm over
20–60 min). Calibrated cold and measured warm, every point it measures is off in scale by that
growth (docs/explanation/metrology.md, "The scanner's warm-up"). Makers give a warm-up time;
this job waits until the scanner has been on that long, and the calibration and scan jobs
warn when they start on a scanner that has not.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from scancell.daemon.jobs.runner import JobContext
from scancell.devices.simulator import ScannerClock
from scancell.protocols.commands import CommandError

#: how often the job reports its progress (s of the scanner's time)
PROGRESS_S = 60.0


class WallScannerClock:
    """A real cell: the daemon cannot see the scanner's power switch, so it counts the scanner
    as switched on when the daemon started, unless told otherwise (``powered_since``)."""

    def __init__(self) -> None:
        self.on_at = time.monotonic()

    def powered_s(self) -> float:
        return time.monotonic() - self.on_at

    def powered_since(self, seconds_ago: float) -> None:
        self.on_at = time.monotonic() - seconds_ago

    async def wait(self, seconds: float) -> None:
        await asyncio.sleep(seconds)


def check_request(req: dict[str, Any], clock: ScannerClock, warmup_min: float | None) -> float:
    """The minutes a warm_up request waits for; CommandError before the job starts if none
    are known, or if it sets a simulated scanner's power-on time."""
    minutes = req.get("minutes", warmup_min)
    if minutes is None:
        raise CommandError("invalid", "warm_up: the cell config names no warm-up time "
                                      "([scanner] warmup_min) and the request gives no minutes")
    if "powered_min" in req and not isinstance(clock, WallScannerClock):
        raise CommandError("invalid", "warm_up: powered_min is for a real cell; the simulated "
                                      "scanner knows when it was switched on")
    return float(minutes)


async def warm_up(ctx: JobContext, clock: ScannerClock, warmup_min: float | None
                  ) -> dict[str, Any]:
    req = ctx.request
    minutes = check_request(req, clock, warmup_min)
    if "powered_min" in req and isinstance(clock, WallScannerClock):
        clock.powered_since(float(req["powered_min"]) * 60.0)
    target_s = float(minutes) * 60.0
    before_s = clock.powered_s()
    left_s = max(0.0, target_s - before_s)
    ctx.event("running", "warm_up", f"scanner on for {before_s / 60:.1f} of its "
              f"{float(minutes):g} min warm-up: waiting {left_s / 60:.1f} min")
    total = int(-(-left_s // PROGRESS_S))
    for i in range(total):
        await clock.wait(max(0.0, min(PROGRESS_S, target_s - clock.powered_s())))
        ctx.event("running", "warm_up", f"scanner on for {clock.powered_s() / 60:.1f} of "
                  f"{float(minutes):g} min", index=i + 1, total=total)
    return {"warmup_min": float(minutes), "powered_min_before": round(before_s / 60.0, 3),
            "waited_min": round(left_s / 60.0, 3),
            "powered_min": round(clock.powered_s() / 60.0, 3)}
