"""Reprocessing 8 recordings as Dask tasks: a local cluster of 1 and of 2 worker processes, and
without Dask (issue 37, item 4).

Recordings: 8 MCAP files, each with 2 scans of the car-body rear rendered once by the simulated
cell at full size (2 x 9 frames of 2448 x 2048 per scan, one exposure), written as the recorder
writes a session. Each Dask worker first reprocesses one small recording (its kernels compile),
and so does this process before the run without Dask; then the clock runs from the first
submission to the last commit (``scancell.batch.reprocess.run``, as ``scancell reprocess``
runs it).

Figures: recordings per minute on 1 and 2 workers; the reference is the 1-worker run of the same
invocation, so the ratio is the speed-up 2 workers give on this 2-core machine. The per-recording
overhead of Dask: (the default local cluster's time - the same recordings reprocessed here one
after another, no Dask) / 8; and the same for 1 worker, whose process runs one thread (Dask
sets OMP_NUM_THREADS=1 in its workers) where the run without Dask uses both cores. The clouds of
every run are compared byte for byte.

Run: .venv/bin/python benchmarks/bench_reprocess_share.py  (or `make bench`)
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.batch.reprocess import reprocess_task, run
from scancell.model.patterns import FringeSequence
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.scan_recording import write_scan_recording
from scancell.workers.reprocess import reprocess

RECORDINGS = 8


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


def on_cluster(n_workers: int, files: list[Path], warm: Path, out: Path) -> float:
    """Seconds for ``files`` on a local cluster of ``n_workers`` worker processes."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster, Client(cluster) as client:
        for k, addr in enumerate(client.scheduler_info()["workers"]):  # compile on each
            client.submit(reprocess_task, str(warm), str(out / f"warm{k}"), None, None,
                          workers=[addr], pure=False).result()
        t0 = time.perf_counter()
        outcomes = run(client, files, [out / f.stem for f in files], None, None)
        seconds = time.perf_counter() - t0
    bad = [o.file.name for o in outcomes if not o.ok]
    if bad:
        raise SystemExit(f"not reprocessed: {bad}")
    used = {o.worker for o in outcomes}
    print(f"  {n_workers} worker(s): {len(files)} recordings in {seconds:.1f} s, by "
          f"{len(used)} worker(s)")
    return seconds


def without_dask(files: list[Path], warm: Path, out: Path) -> float:
    reprocess(warm, out / "warm", progress=False)
    t0 = time.perf_counter()
    for f in files:
        reprocess(f, out / f.stem, progress=False)
    seconds = time.perf_counter() - t0
    print(f"  no Dask : {len(files)} recordings in {seconds:.1f} s, one after another here")
    return seconds


def clouds(folder: Path) -> dict[str, bytes]:
    """The timed recordings' clouds (the warm-ups' left out: one per worker)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.glob("full*/**/*.ply"))}


def main() -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        files = recordings(tmp, 1.0, RECORDINGS, "full")
        warm = recordings(tmp, 8.0, 1, "warm")[0]
        size = sum(f.stat().st_size for f in files) / 1e9
        print(f"{RECORDINGS} recordings of 2 full-size scans ({size:.2f} GB) written in "
              f"{time.perf_counter() - t0:.1f} s; {os.cpu_count()} cores")
        local = without_dask(files, warm, tmp / "local")
        one = on_cluster(1, files, warm, tmp / "one")
        two = on_cluster(2, files, warm, tmp / "two")
        same = (clouds(tmp / "one") == clouds(tmp / "two") == clouds(tmp / "local")
                and clouds(tmp / "one"))
    n = len(files)
    print(f"1 worker : {n / one * 60:6.2f} recordings/min (reference)")
    print(f"2 workers: {n / two * 60:6.2f} recordings/min  ratio {one / two:.2f}")
    print(f"Dask's overhead per recording, the default local cluster (2 workers) against none: "
          f"{(two - local) / n:+.2f} s of {local / n:.2f} s; 1 worker (one thread: Dask sets "
          f"OMP_NUM_THREADS=1) against none: {(one - local) / n:+.2f} s")
    print(f"clouds identical between the three runs: {bool(same)}")
    return {"one_per_min": n / one * 60, "two_per_min": n / two * 60, "ratio": one / two,
            "overhead_s": (two - local) / n}


if __name__ == "__main__":
    main()
