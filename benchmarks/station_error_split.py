"""Split each station's true error into its pose's and its scan's, for a simulated run.

A station's true error is the distance from its points, placed by the ECS and the hand-eye
calibration, to the true part. The simulator logs the pose it rendered each scan at
(``[simulator] true_pose_log``, which `scancell demo` writes to ``<run>/truth/true_poses.jsonl``):
the true left camera's. A cloud is in the MCS the stereo calibration defines, which sits off the
true left camera by a small rigid move (:mod:`scancell.sim.calibration_truth`) that the hand-eye
absorbs. Placed by the true pose after that move, the points' distance to the part is the
scan's error alone (the calibration's non-rigid part, the decoding, the optics). What the
recorded pose adds on top is the pose's (the ECS, the hand-eye, the tracker's location). Per
station (every ``--every``-th point, the world frame, mm):

- ``placed``: mean |distance| with the recorded pose (what the fuse worker's figure measures
  before any refinement);
- ``scan``: mean |distance| with the true pose;
- ``pose``: mean displacement of the points between the two poses, and that move's rotation
  (arcsec) and its shift at the cloud's centroid;
- ``scale``: the scale about the camera (ppm) that brings the truly placed points closest to the
  part, and the scan's error after it: a stereo geometry grown since its calibration (warm-up)
  scales every point's depth, and shows as that scale.

Run: .venv/bin/python benchmarks/station_error_split.py runs/<stamp> [--every 20]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.fusion import FusionError
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.model.transforms import apply_T
from scancell.recorder.reading import samples
from scancell.sim.calibration_truth import calibrated_frame_offset
from scancell.sim.host import sim_cell
from scancell.workers.recorded_stations import recorded_poses, station_cloud
from scancell.workers.reprocess import recorded_simulator

#: a logged pose belongs to a station when its joints lie this close to the station's
#: commanded ones (deg): the simulated arm's repeatability is 0.002 deg a joint, 1 sigma
JOINTS_MATCH_DEG = 0.05


def scan_recording(run: Path) -> Path:
    """The run's recording of its scan job (``scan_part-*.mcap``; the acceptance job's
    recording has stations too, on its artefacts)."""
    for path in sorted((run / "recordings").glob("scan_part-*.mcap"), reverse=True):
        try:
            recorded_poses(path)
        except FusionError:
            continue
        return path
    raise SystemExit(f"{run}/recordings: no scan_part recording with stations")


def read_log(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        raise SystemExit(f"{path}: no true-pose log (a run of `scancell demo` from before the "
                         f"log existed, or a real cell)")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def station_records(recording: Path) -> dict[str, dict[str, Any]]:
    """Each station's ECS record (``scan/<station>/ecs``) by scan id."""
    return {(e := json.loads(s.payload))["scan_id"]: e
            for s in samples(recording, ["scan/*/ecs"])}


def true_pose(log: list[dict[str, Any]], record: dict[str, Any]) -> dict[str, Any] | None:
    """The last pose logged before the station's record whose joints are the station's."""
    q = np.asarray(record["joints_deg"], float)
    for line in reversed(log):
        if line["stamp_ns"] < record["stamp_ns"] and np.abs(
                np.asarray(line["joints_deg"]) - q).max() < JOINTS_MATCH_DEG:
            return line
    return None


def best_scale_ppm(truth: Any, T: np.ndarray, p: np.ndarray, span_ppm: float = 400.0,
                   n: int = 5000) -> tuple[float, float]:
    """The scale of ``p`` (camera frame) about the camera's centre that minimises the mean
    |distance| of ``T`` · scaled points to the part (ppm, searched over ±``span_ppm`` in two
    passes), and that mean (mm); on at most ``n`` points."""
    q = p[:: max(1, len(p) // n)]

    def cost(ppm: float) -> float:
        return float(np.abs(truth(apply_T(T, q * (1.0 + ppm * 1e-6)))).mean())

    grid = np.linspace(-span_ppm, span_ppm, 17)
    best = grid[int(np.argmin([cost(x) for x in grid]))]
    fine = np.linspace(best - span_ppm / 8, best + span_ppm / 8, 11)
    best = fine[int(np.argmin([cost(x) for x in fine]))]
    return float(best), cost(best)


def rotation_arcsec(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) * 3600)


def fused_true_errors(run: Path) -> dict[str, float]:
    """The fuse worker's per-station true error (mm) by station name, if the run has one."""
    path = run / "summary.json"
    stations = json.loads(path.read_text()).get("uncertainty") if path.exists() else None
    return {name: s.get("true_error_mm") for name, s in (stations or {}).items()}


def calibrated_at_s(run: Path) -> float:
    """Sim time (s) of the run's stereo calibration, after the demo's warm-up job
    (``calibration/scanner_warm_up.json``; runs before session 35 calibrated at power-on)."""
    path = run / "calibration" / "scanner_warm_up.json"
    return 60.0 * float(json.loads(path.read_text())["powered_min"]) if path.exists() else 0.0


def simulated_run(run: Path) -> tuple[Path, list[dict[str, Any]], dict[str, Any], Any, Any]:
    """A demo run's scan recording, its true-pose log, the recorded simulator table, the
    simulated cell (for its truth and rig: it renders nothing, so logs nothing) and the
    calibration's offset from the true left camera."""
    recording = scan_recording(run)
    log = read_log(run / "truth" / "true_poses.jsonl")
    simulator = recorded_simulator(recording)
    if simulator is None:
        raise SystemExit(f"{recording}: not a simulated cell's recording: no truth")
    cell = sim_cell(simulator)
    offset = calibrated_frame_offset(cell.rig_at(calibrated_at_s(run)),
                                     StereoCalibration.read(run / "calibration" / "stereo.yaml"))
    return recording, log, simulator, cell, offset


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a `scancell demo` run directory (runs/<stamp>)")
    ap.add_argument("--every", type=int, default=20, help="use every k-th point of a station")
    ap.add_argument("--json", type=Path, help="write the per-station table here")
    a = ap.parse_args()
    recording, log, simulator, cell, offset = simulated_run(a.run)
    truth = cell.surface_distance
    T_true_from_cal = np.linalg.inv(offset.T_cal_from_true)
    poses, hand_eye = recorded_poses(recording)
    T_ecs_from_mcs = np.asarray(hand_eye["T_ecs_from_mcs"], float)
    records = station_records(recording)
    fused = fused_true_errors(a.run)
    print(f"{recording.name}: {len(poses)} stations of part {simulator.get('part')!r}, seed "
          f"{simulator.get('seed', 0)}; the calibration's MCS sits {offset.rotation_arcsec:.1f}″ / "
          f"{offset.translation_mm:.4f} mm off the true left camera (non-rigid RMS "
          f"{offset.residual_rms_mm:.4f} mm)")
    print(f"{'station':>8} {'sim s':>6} {'placed':>8} {'scan':>8} {'pose':>8} {'rot″':>6} "
          f"{'shift':>7} {'ppm':>5} {'scaled':>7} {'fused':>7}  (mm: mean |distance|, "
          f"displacement)")
    rows = []
    for st in poses:
        logged = true_pose(log, records[st.scan_id])
        if logged is None:
            print(f"{st.name:>8}  no logged pose matches its joints: left out")
            continue
        try:
            pts, _ = station_cloud(recording, st)
        except FusionError as exc:  # a job stopped between a station's ECS and its cloud
            print(f"{st.name:>8}  {exc}: left out")
            continue
        p = pts[:: a.every].astype(float)
        T_cam = np.asarray(logged["T_world_from_mcs"], float)
        T_est, T_true = st.T_world_from_ecs @ T_ecs_from_mcs, T_cam @ T_true_from_cal
        ppm, scaled = best_scale_ppm(truth, T_true, p)
        placed, true_placed = apply_T(T_est, p), apply_T(T_true, p)
        move = T_est @ np.linalg.inv(T_true)
        centroid = true_placed.mean(axis=0)
        row = {"station": st.name, "sim_s": logged["sim_s"], "points": len(p),
               "placed_mm": float(np.abs(truth(placed)).mean()),
               "scan_mm": float(np.abs(truth(true_placed)).mean()),
               "pose_mm": float(np.linalg.norm(placed - true_placed, axis=1).mean()),
               "rotation_arcsec": rotation_arcsec(move[:3, :3]),
               "shift_at_centroid_mm": float(np.linalg.norm(apply_T(move, centroid[None])[0]
                                                            - centroid)),
               "scale_ppm": ppm, "scan_scaled_mm": scaled,
               "fused_true_error_mm": fused.get(st.name)}
        rows.append(row)
        f = row["fused_true_error_mm"]
        print(f"{st.name:>8} {row['sim_s']:6.0f} {row['placed_mm']:8.4f} {row['scan_mm']:8.4f} "
              f"{row['pose_mm']:8.4f} {row['rotation_arcsec']:6.1f} "
              f"{row['shift_at_centroid_mm']:7.4f} {ppm:5.0f} {scaled:7.4f} "
              f"{'' if f is None else f'{f:7.4f}'}")
    if not rows:
        return 1
    for key in ("placed_mm", "scan_mm", "pose_mm", "rotation_arcsec", "scale_ppm",
                "scan_scaled_mm"):
        v = np.array([r[key] for r in rows])
        print(f"{key:>18}: mean {v.mean():.4f}, median {np.median(v):.4f}, max {v.max():.4f}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
