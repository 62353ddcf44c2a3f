"""How far off the cluster ECS puts the scanned surface (issue 37: the car body's true error).

The simulated arm with the housing's SMR cluster, through the real tracker protocol (STLP
server and the ``line_tracker`` driver): the arm moves by a few degrees from its start pose
(it rings), the job's ``measure_cluster`` settles on the first SMR and averages five shots of
each SMR it sees, and the scanner's pose is fitted to them with the cluster as built (no
calibration error). Once the arm is still, the fitted pose is compared with the true one at a
point 700 mm in front of the scanner (MCS z: where the scanned surface lies).

Mechanics: ``realistic``; without its vibration (ringing and the hold's); and with every effect
off (the tracker's noise alone, the reference). Printed: the error's mean, 90th percentile and
maximum over ``--moves`` moves, and each row's ratio to the reference.

Run: .venv/bin/python benchmarks/bench_cluster_ecs.py [--moves 20] [--seed 1]
"""

from __future__ import annotations

import argparse
import asyncio

import numpy as np
import scancell.sim.mechanics as mech
from scancell.analysis.smr_cluster import fit_cluster_pose
from scancell.analysis.tracker_network import TrackerSigma
from scancell.daemon.jobs.cluster_measure import measure_cluster
from scancell.daemon.jobs.metrology import MetrologySettings
from scancell.devices.line_tracker import LineTracker
from scancell.model.cell_geometry import CellGeometry
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.optics_profile import optics_profile
from scancell.sim.parts import HOUSING_SMR_CLUSTER
from scancell.sim.tracker_server import TcpTrackerServer

AHEAD_MCS = np.array([0.0, 0.0, 700.0, 1.0])


def errors(off: tuple[str, ...], moves: int, seed: int) -> list[float]:
    cell = SimCell(SimCellConfig(camera_scale=16, part=None, optics=optics_profile("ideal"),
                                 mechanics=mech.mechanics_profile("realistic", off),
                                 smr_cluster=dict(HOUSING_SMR_CLUSTER)))
    geometry = CellGeometry.from_table(cell.planner_table())
    built = {n: c for n, (c, _) in cell.smr_cluster.items()}
    built["rear"] = np.asarray(cell.cfg.smr_in_mcs_mm, float)
    q0 = cell.start_joints()
    rng = np.random.default_rng(seed)

    async def run() -> list[float]:
        server = TcpTrackerServer(cell, port=0)
        await server.start()
        tracker = LineTracker("tracker", {"url": f"socket://127.0.0.1:{server.port}"})
        await tracker.connect()
        out = []
        try:
            while len(out) < moves:
                cell.move_joints(q0 + np.radians(np.r_[rng.uniform(-4, 4, 5), 0.0]), 1.0)
                shots = await measure_cluster(tracker, geometry, cell.q, None, 5, {},
                                              MetrologySettings())
                cell.clock.advance(3.0)  # the arm still, as when it scans
                if len(set(shots.points_mm) & set(built)) < 3:
                    continue
                fit = fit_cluster_pose(built, shots.points_mm, TrackerSigma())
                d = fit.T_world_from_mcs @ AHEAD_MCS - cell.T_world_from_mcs() @ AHEAD_MCS
                out.append(float(np.linalg.norm(d[:3])))
        finally:
            await tracker.close()
            await server.close()
        return out

    return asyncio.run(run())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--moves", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    rows = {"tracker noise alone (reference)": tuple(mech.EFFECTS),
            "realistic without vibration": ("vibration",), "realistic": ()}
    ref = None
    for name, off in rows.items():
        e = errors(off, a.moves, a.seed)
        ref = ref or float(np.mean(e))
        print(f"{name:32s} 700 mm ahead: mean {np.mean(e):.4f} mm, p90 "
              f"{np.percentile(e, 90):.4f}, max {np.max(e):.4f} ({np.mean(e) / ref:.2f}x)")


if __name__ == "__main__":
    main()
