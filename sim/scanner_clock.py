"""The simulated scanner's warm-up clock: it was switched on at sim time 0 (when the cell was
set up), and a cell that waits for it lets sim time pass with nothing moving, so the scanner,
the arm, the tracker's stand and the air all go on warming (sim/mechanics.py)."""

from __future__ import annotations

import asyncio
from typing import Any


class SimScannerClock:
    def __init__(self, world: Any) -> None:
        self.world = world

    def powered_s(self) -> float:
        return self.world.cell.clock.now()

    async def wait(self, seconds: float) -> None:
        def idle() -> None:
            with self.world.lock:
                self.world.cell.clock.advance(seconds)

        await asyncio.to_thread(idle)
