"""Fusion at scale: N full-density stations through the fuse worker over the bus (issue 37).

A ``scancell worker fuse`` process (a zenoh client of this process, which listens as the cell's
router) receives a synthetic ``scan_part`` job: a latched hand-eye (identity), and per station
its ECS (the tracker's three SMR points, shifted with the station) and its cloud of 3.5 M points
(the simulated full-size scanner's density, ~0.12 mm spacing over 225 x 225 mm) sampled from one
gently curved sheet, with 0.02 mm of noise along the sheet's normal and that as each point's
stated 1-sigma. The stations lie on a grid with 30 % overlap on each side, so the sheet grows
with N as a part does. Each station is sent when the last one is fused (its display cloud comes
back on ``fusion/cloud``), then the job's end; the run ends with ``fusion/report``.

Figures for N = 25, 50, 100, 200 (``--stations``): the fuse worker's peak RSS (sampled from
/proc every 0.2 s; its heap, mapped-file and shared-memory parts at that moment, and whether a
station or the report was under way) and its growth per station (least squares over the RSS
after each station), the time per station (median, and the spread of the last half against the
first), and the time from the job's end to the report. Issue 37 asks ≤ 1.5 GB at every N, ≤ 2 MB
per station, time per station flat within ±20 %. A run whose fuse worker passes ``--cap-gb`` is
stopped and reported as such (before issue 37 the fuse worker kept ~0.5 GB a station).

Run: .venv/bin/python benchmarks/bench_fusion_scale.py [--stations 25,50,100,200] [--cap-gb 12]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from proc_memory import rss_mb, rss_split_mb
from scancell.bus.ports import free_port
from scancell.bus.zenoh_bus import Bus, BusConfig
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import Attachment

POINTS = 3_500_000
SIDE_MM = 225.0
STEP_MM = SIDE_MM * 0.7  # 30 % overlap with each neighbour
SMR = np.array([[2900.0, 100.0, 300.0], [2950.0, 180.0, 330.0], [2860.0, 160.0, 260.0]])
STANDOFF_MM = 650.0


def sheet_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The part: a sheet curving gently (radius ~20 m) with a 2 mm swell every 400 mm."""
    return (x * x + y * y) / 40_000.0 + 2.0 * np.sin(x / 64.0) * np.cos(y / 64.0)


def station_offset(i: int, n: int) -> np.ndarray:
    cols = int(np.ceil(np.sqrt(n)))
    return np.array([(i % cols) * STEP_MM, (i // cols) * STEP_MM, 0.0])


def station_cloud(i: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(points in the station's mcs, 1-sigma): the sheet under station i minus its offset."""
    rng = np.random.default_rng(i)
    off = station_offset(i, n)
    xy = rng.uniform(-SIDE_MM / 2, SIDE_MM / 2, (POINTS, 2)) + off[:2]
    z = sheet_z(xy[:, 0], xy[:, 1]) + rng.normal(0.0, 0.02, POINTS)
    world = np.column_stack([xy, z + STANDOFF_MM]).astype(np.float32)
    return world - off.astype(np.float32), np.full(POINTS, 0.02, np.float32)


def run(n: int, cap_gb: float, tmp: Path) -> dict:
    cell = f"fs{os.getpid()}{n}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hub = Bus.open(BusConfig(listen=(endpoint,)), cell)
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    worker = subprocess.Popen([sys.executable, "-m", "scancell", "worker", "fuse", "--out",
                               str(tmp / f"n{n}"), "--no-mesh"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    peak, stop = [0.0], threading.Event()
    phase, at_peak = ["start"], {}

    def sample() -> None:
        while not stop.is_set():
            rss = rss_mb(worker.pid)
            if rss > peak[0]:
                peak[0] = rss
                at_peak.update(rss_split_mb(worker.pid), phase=phase[0])
            stop.wait(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    fused, reports = [], []
    hub.subscribe(hub.keys.fusion_cloud, lambda s: fused.append(
        (time.monotonic(), s.attachment.meta.get("stations"))))
    hub.subscribe(hub.keys.fusion_report, lambda s: reports.append(s.decode()))
    he = hub.latched(hub.keys.hand_eye)
    he.publish(messages.encode_json({"T_ecs_from_mcs": np.eye(4).tolist(),
                                     "j6_angles_deg": [120.0, -120.0], "rms_mm": 0.0,
                                     "job_id": "he"}, "scancell.HandEye"))
    job = f"scan_part-scale-{n}"
    deadline = time.monotonic() + 60
    while not hub.members(hub.keys.worker("fuse", "*")):
        if time.monotonic() > deadline or worker.poll() is not None:
            raise SystemExit("the fuse worker did not come up")
        time.sleep(0.3)
    times, rss_after, capped = [], [], None
    try:
        for i in range(n):
            station = f"s{i:03d}"
            phase[0] = f"station {i}"
            mcs, sigma = station_cloud(i, n)
            t0 = time.monotonic()
            hub.publish_json(hub.keys.station_ecs(station), {
                "job_id": job, "station": station, "scan_id": f"{job}-{station}",
                "points_mm": (SMR + station_offset(i, n)).tolist(), "j6_deg": [0.0, 120.0, -120.0],
                "stamp_ns": messages.now_ns()}, "scancell.StationEcs")
            stamp = messages.now_ns()
            hub.publish(hub.keys.scan_cloud(station), fg.encode_proto(fg.point_cloud(
                mcs, stamp, f"mcs_{station}", {"uncertainty": sigma})), Attachment(stamp, i, None, {
                    "job_id": job, "station": station, "scan_id": f"{job}-{station}",
                    "job_kind": "scan_part"}))
            while not any(m == i + 1 for _, m in fused):
                if worker.poll() is not None:
                    raise SystemExit(f"the fuse worker died at station {i} (exit {worker.returncode})")
                if peak[0] > cap_gb * 1024:
                    capped = i
                    break
                time.sleep(0.02)
            if capped is not None:
                break
            times.append(time.monotonic() - t0)
            rss_after.append(rss_mb(worker.pid))
        done = len(times)
        t_end = time.monotonic()
        if capped is None:
            phase[0] = "report"
            hub.publish_json(hub.keys.job_event(job), {
                "job_id": job, "kind": "scan_part", "state": "done", "step": "done", "message": "",
                "index": None, "total": None, "stamp_ns": messages.now_ns(),
                "result": {"stations": [{"station": f"s{i:03d}"} for i in range(n)]}},
                "scancell.JobEvent")
            while not reports and worker.poll() is None:
                time.sleep(0.1)
        report_s = time.monotonic() - t_end
    finally:
        stop.set()
        sampler.join()
        worker.terminate()
        worker.wait(60)
        he.close()
        hub.close()
    slope = float(np.polyfit(np.arange(len(rss_after)), rss_after, 1)[0]) if len(rss_after) > 2 else 0.0
    half = len(times) // 2
    drift = (statistics.median(times[half:]) / statistics.median(times[:half]) - 1.0
             if half >= 2 else float("nan"))
    return {"n": n, "done": done, "capped": capped, "peak_mb": peak[0], "mb_per_station": slope,
            "s_per_station": statistics.median(times) if times else float("nan"),
            "drift": drift, "report_s": report_s if capped is None else None,
            "report": (reports or [{}])[0], "at_peak": at_peak}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stations", default="25,50,100,200")
    ap.add_argument("--cap-gb", type=float, default=12.0)
    args = ap.parse_args()
    print(f"{'N':>4s} {'fused':>5s} {'peak MB':>8s} {'MB/station':>10s} {'s/station':>9s} "
          f"{'drift':>6s} {'report s':>8s}   (issue: <= 1500 MB, <= 2 MB/station, drift +-20 %)")
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(x) for x in args.stations.split(",")):
            r = run(n, args.cap_gb, Path(tmp))
            note = (f"   stopped: the fuse worker passed {args.cap_gb:g} GB at station {r['capped']}"
                    if r["capped"] is not None else "")
            rep = f"{r['report_s']:8.1f}" if r["report_s"] is not None else f"{'-':>8s}"
            print(f"{n:4d} {r['done']:5d} {r['peak_mb']:8.0f} {r['mb_per_station']:10.2f} "
                  f"{r['s_per_station']:9.2f} {100 * r['drift']:+5.0f}% {rep}{note}", flush=True)
            split = r["at_peak"]
            if split:
                print(f"{'':4s} at the peak ({split['phase']}): {split['anon']:.0f} MB heap, "
                      f"{split['file']:.0f} MB mapped files, {split['shmem']:.0f} MB shared memory",
                      flush=True)
            ok &= r["capped"] is None and r["peak_mb"] <= 1500 and r["mb_per_station"] <= 2.0
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
