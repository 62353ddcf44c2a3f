"""Tracker links on loopback: measure round trip of the emScon driver against its emulator, and
of the STLP line driver against its server (the reference, measured in the same run); then
commands through injected faults (beam break, busy, disconnect), none of which may hang
(issue 38: round trip <= 5 ms; 0 hung commands).

The simulated shot takes no time here (``tracker_shot_s = 0``): the figure is the link's own
cost (encode, TCP, the server's answer, decode, the asyncio hand-over), not the instrument's.

Run: .venv/bin/python benchmarks/bench_tracker_link.py  (or `make bench`)
"""

from __future__ import annotations

import asyncio
import dataclasses
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scancell.devices.emscon_tracker import EmsconTracker
from scancell.devices.errors import DeviceError, Timeout
from scancell.devices.line_tracker import LineTracker
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.emscon_server import EmsconServer
from scancell.sim.mechanics import mechanics_profile
from scancell.sim.tracker_server import TcpTrackerServer

SHOTS = 300
FAULT_ROUNDS = 30


def cell() -> SimCell:
    mech = dataclasses.replace(mechanics_profile("ideal"), tracker_shot_s=0.0, tracker_find_s=0.0)
    c = SimCell(SimCellConfig(camera_scale=16, seed=1, mechanics=mech))
    c.move_joints(c.ik_for_mcs(c.mcs_pose_looking_at(c.cfg.T_world_from_part[:3, 3])))
    return c


async def round_trips(server_class, driver_class) -> list[float]:
    server = server_class(cell())
    await server.start()
    trk = driver_class("tracker", {"url": f"socket://127.0.0.1:{server.port}"})
    await trk.connect()
    try:
        for _ in range(20):
            await trk.measure()
        out = []
        for _ in range(SHOTS):
            t0 = time.perf_counter()
            await trk.measure()
            out.append(1000 * (time.perf_counter() - t0))
        return out
    finally:
        await trk.close()
        await server.close()


async def faults() -> dict[str, int]:
    c = cell()
    server = EmsconServer(c)
    await server.start()
    trk = EmsconTracker("tracker", {"url": f"socket://127.0.0.1:{server.port}",
                                    "timeout_s": 2.0})
    await trk.connect()
    counts = {"commands": 0, "ok": 0, "typed_errors": 0, "hung": 0}

    async def one(coro) -> None:
        counts["commands"] += 1
        try:
            async with asyncio.timeout(5.0):  # beyond the driver's own 2 s: a hang
                await coro
            counts["ok"] += 1
        except Timeout:
            counts["hung"] += 1
        except DeviceError:
            counts["typed_errors"] += 1
        except TimeoutError:
            counts["hung"] += 1

    try:
        for _ in range(FAULT_ROUNDS):
            for fault in ("beam_break", "busy", "reflector_lost"):
                server.handler.fault = fault
                await one(trk.measure())
                await one(trk.status())
                await one(trk.find_reflector(c.smr_center_world()))
            server.handler.fault = None
            await one(trk.find_reflector(c.smr_center_world()))
            await one(trk.measure())
            server.drop_clients()
            await asyncio.sleep(0.05)
            await one(trk.measure())
            await one(trk.connect())
            await one(trk.measure())
    finally:
        await trk.close()
        await server.close()
    return counts


def main() -> int:
    line = asyncio.run(round_trips(TcpTrackerServer, LineTracker))
    emscon = asyncio.run(round_trips(EmsconServer, EmsconTracker))
    f = asyncio.run(faults())
    med_line, med_em = statistics.median(line), statistics.median(emscon)
    p99 = sorted(emscon)[int(0.99 * len(emscon))]
    print(f"measure round trip over {SHOTS} shots on loopback (simulated shot 0 s)")
    print("| link | median (ms) | p99 (ms) | max (ms) | median / STLP |")
    print("|---|---|---|---|---|")
    print(f"| STLP line driver (reference) | {med_line:.2f} | "
          f"{sorted(line)[int(0.99 * len(line))]:.2f} | {max(line):.2f} | 1.00 |")
    print(f"| emScon driver | {med_em:.2f} | {p99:.2f} | {max(emscon):.2f} | "
          f"{med_em / med_line:.2f} |")
    print(f"\nfault injections ({FAULT_ROUNDS} rounds of beam break, busy, reflector lost, "
          f"disconnect): {f['commands']} commands, {f['ok']} answered, {f['typed_errors']} "
          f"typed errors, {f['hung']} hung")
    return 0 if f["hung"] == 0 and med_em <= 5.0 else 1


if __name__ == "__main__":
    sys.exit(main())
