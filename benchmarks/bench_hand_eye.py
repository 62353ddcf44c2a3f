"""Hand-eye calibration on the simulated cell against the true mounting (issue 6).

The real path: a daemon on the sim cell runs ``cmd/job/calibrate_hand_eye`` (the world places
the ball; coupled scans; tracker measurements; J6 turns for the ECS), the scan worker decodes
the ball scans, the calibrate worker detects the balls and solves ``T_ecs_from_mcs``. The
result is compared with the simulator's true ``T_ecs_from_mcs`` for the same J6 turn angles.
Configurations vary the number of balls and their spread. Targets: rotation <= 15",
translation <= 0.05 mm. Cameras at 1/2 resolution (1224 x 1024) to keep the run short.

Run: .venv/bin/python benchmarks/bench_hand_eye.py  (or `make bench`)
"""

from __future__ import annotations

import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scancell.analysis.handeye import rotation_angle_arcsec
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.bus import Bus, BusConfig
from scancell.client import CellClient
from scancell.sim.world import get_world
from scancell.workers.calibrate import CalibrateWorker
from scancell.workers.scan import ScanWorker

from tests.conftest import DaemonThread, free_port, sim_cell_raw, wait_until

SCALE = 2.0
CONFIGS = [("15 balls, spread 120 x 100 mm", {"balls": 15}),
           ("8 balls, spread 120 x 100 mm", {"balls": 8}),
           ("15 balls, spread 60 x 50 mm", {"balls": 15, "spread_mm": [60, 50]}),
           ("15 balls, depth 600-640 mm only", {"balls": 15, "depths_mm": [600, 640]})]


def run(request: dict) -> dict[str, float]:
    cell, ep = "b" + uuid.uuid4().hex[:8], f"tcp/127.0.0.1:{free_port()}"
    d = DaemonThread(sim_cell_raw(SCALE), cell, ep)
    client = CellClient(cell, ep, timeout_s=60)
    bus = Bus.open(BusConfig.for_client(ep), cell)
    try:
        wait_until(lambda: all(s["state"] == "connected"
                               for s in client.status()["devices"].values()), 60)
        world = get_world(d.cfg.simulator["world"])
        with tempfile.TemporaryDirectory() as tmp:
            world.cell.rig.write_opencv_yaml(Path(tmp) / "s.yaml")
            sw = ScanWorker(bus, StereoCalibration.read(Path(tmp) / "s.yaml"))
            cw = CalibrateWorker(bus, Path(tmp))
            sw.start()
            cw.start()
            t0 = time.perf_counter()
            client.call("job/calibrate_hand_eye", request)
            wait_until(lambda: cw.results, 900, period_s=0.5, what="hand-eye result")
            elapsed = time.perf_counter() - t0
            res = cw.results[0]
            cw.stop()
            sw.stop()
        T = np.array(res["T_ecs_from_mcs"])
        truth = world.cell.true_T_ecs_from_mcs(tuple(res["j6_angles_deg"][:2]))
        return {"rotation_error_arcsec": rotation_angle_arcsec(T[:3, :3] @ truth[:3, :3].T),
                "translation_error_mm": float(np.linalg.norm(T[:3, 3] - truth[:3, 3])),
                "rms_mm": res["rms_mm"], "rot_sigma": res["rotation_sigma_arcsec"],
                "trans_sigma": res["translation_sigma_mm"], "pairs": res["pairs"],
                "excluded": len(res["excluded"]), "seconds": elapsed}
    finally:
        bus.close()
        client.close()
        d.stop()


def main() -> dict[str, float]:
    print(f"{'configuration':34s} {'rot err':>8s} {'trans err':>10s} {'RMS':>7s} "
          f"{'rot 1s':>7s} {'tr 1s':>7s} {'pairs':>6s} {'excl':>5s} {'s':>6s}")
    out = {}
    for name, req in CONFIGS:
        r = run(req)
        print(f"{name:34s} {r['rotation_error_arcsec']:7.1f}\" {r['translation_error_mm']:8.4f}mm "
              f"{r['rms_mm']:7.4f} {r['rot_sigma']:6.1f}\" {r['trans_sigma']:7.4f} "
              f"{r['pairs']:6d} {r['excluded']:5d} {r['seconds']:6.0f}", flush=True)
        out[name] = r["rotation_error_arcsec"]
    print("targets: rotation <= 15\", translation <= 0.05 mm")
    return out


if __name__ == "__main__":
    main()
