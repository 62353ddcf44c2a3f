"""Seconds per station of a scan_part job at full size, and where the CPU goes (issue 19).

The real path at 2448 x 2048: ``scancell daemon`` on the packaged sim.toml (realistic profile,
HDR exposures, SMR cluster on the scanner housing), ``scancell worker scan`` and
``scancell worker fuse`` (no mesh) and ``scancell record`` as their own processes, a plan of
``STATIONS`` cluster stations on the car rear. The true stereo calibration and hand-eye stand in
for the calibration jobs (they have their own benchmarks). The job keeps sim.toml's nest checks
(start, every 4 stations, end) and scanner check: they are in the job's time, not in the
stations' stage clocks.

Figures: each station's stage clock (move, tracker, scan) from its ``StationEcs`` record, the
job's seconds per station, the time from the job's end to the fusion report, and each process's
CPU seconds over the job. Reference, same run: rendering one station's images in-process (2
cameras x 9 patterns at one pose, one exposure); the ratio is seconds per station over it.

Run: .venv/bin/python benchmarks/bench_station_time.py [--stations N]  (or `make bench`)
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from pathlib import Path

import numpy as np
from scancell.bus import BusConfig
from scancell.bus.ports import free_port
from scancell.client import CellClient
from scancell.deploy import cell_config_path
from scancell.model.patterns import FringeSequence
from scancell.protocols import messages
from scancell.sim.host import flatten_overrides, relocated_ports, sim_cell

#: the part's rear face, one station per target (world, mm; the car rear sits at x ~ 3300)
TARGETS = [(-150.0, -250.0, 0.0), (-150.0, 0.0, 0.0), (-150.0, 250.0, 0.0), (-150.0, 0.0, 150.0)]
TICKS = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (its threads included)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def reference_render() -> float:
    cell = sim_cell({"camera_scale": 1})
    target = cell.cfg.T_world_from_part[:3, 3] + [-200.0, 0, 0]
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(target, 600.0)))
    cell.load_sequence(FringeSequence())
    t0 = time.perf_counter()
    for cam in ("left", "right"):
        cell.render_sequence(cam)
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--stations", type=int, default=3, choices=range(1, len(TARGETS) + 1))
    args = ap.parse_args()
    raw = tomllib.loads(cell_config_path("sim").read_text())
    simulator = {**raw["simulator"], "camera_scale": 1, "smr_cluster": "housing"}
    sets = [*flatten_overrides(relocated_ports(raw, lambda _old: free_port())),
            "simulator.camera_scale=1", "simulator.smr_cluster=housing"]
    cell_name = raw["cell"]["name"]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell_name)
    work = Path(tempfile.mkdtemp(prefix="bench_station_"))
    truth = sim_cell(simulator)
    truth.rig.write_opencv_yaml(work / "stereo.yaml")
    procs: dict[str, subprocess.Popen] = {}

    def start(name: str, *cli: str) -> None:
        procs[name] = subprocess.Popen([sys.executable, "-m", "scancell", *cli], env=env,
                                       stdout=open(work / f"{name}.log", "w"),
                                       stderr=subprocess.STDOUT)

    print("reference: one station's images rendered in-process ...", flush=True)
    ref_s = reference_render()
    print(f"reference: {ref_s:.1f} s (2 cameras x 9 patterns, 2448 x 2048)", flush=True)
    start("daemon", "daemon", "--config", str(cell_config_path("sim")), "--listen", endpoint,
          *[a for s in sets for a in ("--set", s)])
    client = CellClient(cell_name, bus_config=BusConfig.for_client(endpoint), connect_wait_s=60,
                        timeout_s=600)
    try:
        deadline = time.monotonic() + 120
        while not all(s["state"] == "connected" for s in client.status()["devices"].values()):
            if time.monotonic() > deadline:
                raise RuntimeError("the daemon's devices did not connect")
            time.sleep(0.5)
        he = client.bus.latched(client.bus.keys.hand_eye)
        cluster = {n: {"mcs_mm": c.tolist(), "sigma_mm": [0.005] * 3}
                   for n, (c, _) in truth.smr_cluster.items()}
        cluster["rear"] = {"mcs_mm": truth.cfg.smr_in_mcs_mm.tolist(), "sigma_mm": [0.005] * 3}
        he.publish(messages.encode_json({
            "T_ecs_from_mcs": truth.true_T_ecs_from_mcs((120.0, -120.0)).tolist(),
            "j6_angles_deg": [120.0, -120.0], "rms_mm": 0.0, "job_id": "truth",
            "smr_cluster": cluster}, "scancell.HandEye"))
        start("worker-scan", "worker", "scan", "--calib", str(work / "stereo.yaml"))
        start("worker-fuse", "worker", "fuse", "--out", str(work / "fused"), "--no-mesh")
        start("recorder", "record", "--dir", str(work / "rec"))
        time.sleep(8.0)
        centre = truth.cfg.T_world_from_part[:3, 3]
        stations = []
        for i, t in enumerate(TARGETS[: args.stations]):
            q = truth.ik_for_mcs(truth.mcs_pose_looking_at(centre + np.asarray(t), 600.0))
            stations.append({"name": f"s{i + 1:02d}", "joints_deg": np.degrees(q).tolist(),
                             "ecs": "cluster"})
        plan = {"plan": {"name": "bench", "speed": 0.5, "tracker_repeats": 2},
                "station": stations}
        records: list[dict] = []
        reports: list[dict] = []
        lock = threading.Lock()
        client.bus.subscribe(client.bus.keys.station_ecs("*"),
                             lambda s: records.append(s.decode()))
        client.bus.subscribe(client.bus.keys.fusion_report, lambda s: reports.append(s.decode()))
        cpu0 = {n: cpu_s(p.pid) for n, p in procs.items()}
        t0 = time.monotonic()
        final = client.run_job("scan_part", {"plan": plan}, timeout_s=300 * args.stations + 300)
        t_job = time.monotonic() - t0
        while not reports and time.monotonic() - t0 < t_job + 600:
            time.sleep(0.5)
        t_report = time.monotonic() - t0
        cpu = {n: cpu_s(p.pid) - cpu0[n] for n, p in procs.items()}
        if final.get("state") != "done":
            print(f"job {final.get('state')}: {final.get('error')}")
            return 1
        with lock:
            mine = [r for r in records if r.get("job_id") == final["job_id"]]
        print(f"\n{args.stations} stations at 2448 x 2048, realistic profile, cluster ECS")
        print("| station | move s | tracker s | scan s | exposures |")
        print("|---|---|---|---|---|")
        for r in mine:
            tm = r.get("timing_s", {})
            print(f"| {r['station']} | {tm.get('move', 0):.1f} | {tm.get('tracker', 0):.1f} | "
                  f"{tm.get('scan', 0):.1f} | {r.get('exposures_us') or ''} |")
        per = t_job / args.stations
        print(f"\njob {t_job:.1f} s: {per:.1f} s per station; fusion report "
              f"{t_report - t_job:.1f} s after the job's end"
              + ("" if reports else " (never came)"))
        print("CPU seconds over the job and its fusion: " + ", ".join(
            f"{n} {c:.1f}" for n, c in cpu.items()) + f" (wall {t_report:.1f} s, 2 cores)")
        print(f"reference render {ref_s:.1f} s; ratio s per station / reference "
              f"{per / ref_s:.2f}")
        return 0
    finally:
        client.close()
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs.values():
            try:
                p.wait(60)
            except subprocess.TimeoutExpired:
                p.kill()


if __name__ == "__main__":
    raise SystemExit(main())
