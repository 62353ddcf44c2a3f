"""Reprocessing 4 recordings with 1 and 2 reprocess worker processes over zenoh (issue 22).

Recordings: 4 MCAP files, each with 2 scans of the car-body rear rendered once by the simulated
cell at full size (2 x 9 frames of 2448 x 2048 per scan, one exposure), written as the recorder
writes a session. The bench process is the router (the listening peer) and the batch's
coordinator (``ReprocessBatch``, as ``scancell reprocess --bus`` runs it); the workers are
``scancell worker reprocess`` processes. Each worker first reprocesses one small recording (its
kernels compile), then the clock runs from the offer to the last result.

Figures: recordings per minute with 1 and 2 workers; the reference is the 1-worker run of the
same invocation, so the ratio is the speed-up 2 workers give on this machine. The clouds of both
runs are compared byte for byte.

Run: .venv/bin/python benchmarks/bench_reprocess_share.py  (or `make bench`)
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.bus.ports import free_port
from scancell.bus.zenoh_bus import Bus, BusConfig
from scancell.model.patterns import FringeSequence
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.scan_recording import write_scan_recording
from scancell.workers.reprocess_batch import ReprocessBatch

RECORDINGS = 4


def render(scale: float) -> tuple[list[dict], SimCell]:
    cell = SimCell(SimCellConfig(camera_scale=scale))
    centre = cell.cfg.T_world_from_part[:3, 3]
    cell.load_sequence(FringeSequence())
    scans = []
    for dx in (-200.0, 200.0):
        cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(centre + np.array([dx, 0.0, 0.0]), 600.0)))
        scans.append({"left": cell.render_sequence("left"),
                      "right": cell.render_sequence("right")})
    return scans, cell


def recordings(folder: Path, scale: float, n: int, name: str) -> list[Path]:
    scans, cell = render(scale)
    cell.rig.write_opencv_yaml(folder / f"{name}.yaml")
    calib = StereoCalibration.read(folder / f"{name}.yaml")
    paths = [folder / f"{name}{k}.mcap" for k in range(n)]
    for k, p in enumerate(paths):
        write_scan_recording(p, "bench", calib, scans, f"{name}{k}")
    return paths


def run(n_workers: int, files: list[Path], warm: list[Path], out: Path) -> float:
    """Recordings per minute with ``n_workers`` reprocess worker processes."""
    cell = f"bench{uuid.uuid4().hex[:8]}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = Bus.open(BusConfig(listen=(endpoint,)), cell)
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    procs = [subprocess.Popen([sys.executable, "-m", "scancell", "worker", "reprocess"],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
             for _ in range(n_workers)]
    try:
        deadline = time.monotonic() + 120
        while len(bus.members(bus.keys.worker("reprocess", "*"))) < n_workers:
            if time.monotonic() > deadline:
                raise SystemExit(f"fewer than {n_workers} reprocess workers came up")
            time.sleep(0.5)
        ReprocessBatch(bus, [(f, out / "warm" / f.stem) for f in warm[:n_workers]],
                       on_event=lambda line: None).run()
        t0 = time.perf_counter()
        tasks = ReprocessBatch(bus, [(f, out / f.stem) for f in files],
                               on_event=lambda line: None).run()
        seconds = time.perf_counter() - t0
        bad = [t.path for t in tasks if t.state != "done"]
        if bad:
            raise SystemExit(f"not reprocessed: {bad}")
        used = {a["worker"] for t in tasks for a in t.attempts if a["state"] == "ok"}
        print(f"  {n_workers} worker(s): {len(files)} recordings in {seconds:.1f} s, "
              f"by {len(used)} worker(s)")
        return len(files) / seconds * 60.0
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(30)
        bus.close()


def clouds(folder: Path) -> dict[str, bytes]:
    """The timed recordings' clouds (the warm-up's left out: one per worker)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*.ply"))
            if "warm" not in p.relative_to(folder).parts}


def main() -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        files = recordings(tmp, 1.0, RECORDINGS, "full")
        warm = recordings(tmp, 8.0, 2, "warm")
        size = sum(f.stat().st_size for f in files) / 1e9
        print(f"{RECORDINGS} recordings of 2 full-size scans ({size:.2f} GB) written in "
              f"{time.perf_counter() - t0:.1f} s; {os.cpu_count()} cores")
        one = run(1, files, warm, tmp / "one")
        two = run(2, files, warm, tmp / "two")
        same = clouds(tmp / "one") == clouds(tmp / "two") and clouds(tmp / "one")
    print(f"1 worker : {one:6.2f} recordings/min (reference)")
    print(f"2 workers: {two:6.2f} recordings/min  ratio {two / one:.2f}")
    print(f"clouds identical between the runs: {bool(same)}")
    return {"one_per_min": one, "two_per_min": two, "ratio": two / one}


if __name__ == "__main__":
    main()
