"""Decode throughput with 1 and 2 scan worker processes sharing the work over zenoh (issue 22).

Scene: one car-body-rear station rendered once by the simulated cell at full size (2 x 9 frames
of 2448 x 2048, one exposure), published as ``SCANS`` scans under different scan ids. The bench
process is the listening peer (the daemon's role); the workers are ``scancell worker scan``
processes connected as its clients. Each worker first decodes one scan it owns (its kernels
compile), then the clock runs from the first frame published to the last result.

Figures: stations per minute with 1 and 2 workers; the reference is the 1-worker run of the
same invocation, so the ratio is the speed-up 2 workers give on this machine.

Run: .venv/bin/python benchmarks/bench_work_share.py  (or `make bench`)
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np
from scancell.bus.ports import free_port
from scancell.bus.zenoh_bus import Bus, BusConfig
from scancell.cli.ctl import live_workers
from scancell.model.patterns import FringeSequence
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.scan_recording import scan_frames
from scancell.workers.work_share import owner_of

SCANS = 8


def render() -> tuple[dict[str, list[np.ndarray]], SimCell]:
    cell = SimCell(SimCellConfig(camera_scale=1))
    target = cell.cfg.T_world_from_part[:3, 3] + [-200.0, 0, 0]
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(target, 600.0)))
    cell.load_sequence(FringeSequence())
    return {"left": cell.render_sequence("left"), "right": cell.render_sequence("right")}, cell


def publish_scan(bus: Bus, scan_id: str, frames: dict[str, list[np.ndarray]]) -> None:
    for cam, encoded, att in scan_frames(scan_id, scan_id.rsplit("-", 1)[-1], frames, "bench",
                                         "bench"):
        bus.publish(bus.keys.dev(cam, "image"), encoded, att)


def run(n_workers: int, frames: dict[str, list[np.ndarray]], calib: Path) -> float:
    """Stations per minute with ``n_workers`` scan worker processes."""
    cell = f"bench{uuid.uuid4().hex[:8]}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = Bus.open(BusConfig(listen=(endpoint,)), cell)
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    procs = [subprocess.Popen([sys.executable, "-m", "scancell", "worker", "scan", "--calib",
                               str(calib)], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL) for _ in range(n_workers)]
    results: list[str] = []
    lock = threading.Lock()

    def on_result(s) -> None:
        with lock:
            results.append(s.decode()["scan_id"])

    bus.subscribe(bus.keys.scan_result("*"), on_result)
    try:
        deadline = time.monotonic() + 120
        while len(workers := [w["worker"] for w in live_workers(bus) if w["kind"] == "scan"]) \
                < n_workers:
            if time.monotonic() > deadline:
                raise SystemExit(f"only {len(workers)} of {n_workers} workers came up")
            time.sleep(0.5)
        warm = []
        for w in workers:  # one scan each worker owns: its kernels compile off the clock
            warm.append(next(f"warm-{w}-{k}" for k in range(1000)
                             if owner_of(f"warm-{w}-{k}", workers) == w))
        for sid in warm:
            publish_scan(bus, sid, frames)
        _wait(results, lock, len(warm), 300)
        with lock:
            results.clear()
        t0 = time.perf_counter()
        for k in range(SCANS):
            publish_scan(bus, f"run-s{k:02d}", frames)
        _wait(results, lock, SCANS, 600)
        seconds = time.perf_counter() - t0
        with lock:
            assert sorted(results) == [f"run-s{k:02d}" for k in range(SCANS)], results
        return SCANS / seconds * 60.0
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(30)
        bus.close()


def _wait(results: list[str], lock: threading.Lock, n: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        with lock:
            if len(results) >= n:
                return
        if time.monotonic() > deadline:
            raise SystemExit(f"{len(results)} of {n} results after {timeout_s} s")
        time.sleep(0.05)


def main() -> dict[str, float]:
    t0 = time.perf_counter()
    frames, cell = render()
    print(f"rendered 2 x 9 frames of {frames['left'][0].shape[1]} x "
          f"{frames['left'][0].shape[0]} in {time.perf_counter() - t0:.1f} s; {SCANS} scans "
          f"per run, {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory() as tmp:
        calib = Path(tmp) / "stereo.yaml"
        cell.rig.write_opencv_yaml(calib)
        one = run(1, frames, calib)
        two = run(2, frames, calib)
    print(f"1 worker : {one:6.1f} stations/min (reference)")
    print(f"2 workers: {two:6.1f} stations/min  ratio {two / one:.2f}")
    return {"one_per_min": one, "two_per_min": two, "ratio": two / one}


if __name__ == "__main__":
    main()
