"""Trace a simulated run's outliers to their mechanism: which stations make the points farther
than ``--threshold`` from the true surface, where they lie, and what each one's pixel sees.

Every station's cloud is placed by the simulator's true pose (as
``benchmarks/station_error_split.py`` does: the calibration's small rigid offset taken out), so
what is left is the scan's own error. For each point beyond the threshold, the true scene is
ray-cast along the left camera's ray through it (the pixel that made it) and around it:

- ``depth_edge``: the true depth within ±2 px of the pixel spans more than ``--edge-mm``: the
  pixel's footprint (its blur) mixes two surfaces (a mixed pixel);
- ``right_occluded``: the right camera does not see the true surface point: the stereo match
  was made across an occlusion;
- ``shadow``: the projector does not light the true surface point: its phase came from the
  light around it;
- ``grazing``: the left or the right camera sees the true surface beyond ``--grazing-deg`` from
  its normal;
- ``other``: none of these (a phase or unwrapping error on a plainly seen surface).

Run: .venv/bin/python benchmarks/outlier_trace.py runs/<stamp> [--threshold 0.5] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.fusion import FusionError
from scancell.model.transforms import apply_T
from scancell.workers.recorded_stations import recorded_poses, station_cloud

sys.path.insert(0, str(Path(__file__).resolve().parent))
from station_error_split import simulated_run, station_records, true_pose

MECHANISMS = ("depth_edge", "right_occluded", "shadow", "grazing", "other")


def rotate_about(d: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Unit vectors ``d`` (N, 3) turned by ``angle`` (rad) about the unit ``axis``."""
    c, s = np.cos(angle), np.sin(angle)
    return d * c + np.cross(axis, d) * s + np.outer(d @ axis, axis) * (1 - c)


def classify(cell: Any, rig: Any, T_left: np.ndarray, X: np.ndarray, edge_mm: float,
             grazing_deg: float) -> dict[str, np.ndarray]:
    """Per outlier (world points ``X``, N x 3) what its left pixel sees (see the module doc)."""
    c = T_left[:3, 3]
    d = (X - c) / np.linalg.norm(X - c, axis=1, keepdims=True)
    hit = cell.scene.cast(c, d)
    t = hit.t.astype(float)
    P = c + d * t[:, None]
    n = hit.normal.astype(float)
    pix = 1.0 / rig.left.K[0, 0]
    spread = np.zeros(len(X))
    for axis in (T_left[:3, 0], T_left[:3, 1]):
        for k in (-2, -1, 1, 2):
            tk = cell.scene.cast(c, rotate_about(d, axis, k * pix)).t.astype(float)
            spread = np.maximum(spread, np.abs(np.where(np.isfinite(tk), tk, 1e9) - t))
    unseen = [o.name for o in cell.scene.objects if not o.visible_to_cameras]
    T_right = T_left @ rig.T_mcs_from_right
    T_proj = T_left @ rig.T_mcs_from_projector
    X_left = (X - c) @ T_left[:3, :3]
    uv = rig.left.project(X_left)
    out = {"true_depth_mm": t, "error_along_ray_mm": np.linalg.norm(X - c, axis=1) - t,
           "depth_spread_mm": spread, "left_u_px": uv[:, 0], "left_v_px": uv[:, 1]}
    for name, T in (("right", T_right), ("projector", T_proj)):
        v = P - T[:3, 3]
        dist = np.linalg.norm(v, axis=1)
        blocked = cell.scene.occluded(T[:3, 3], v / dist[:, None], dist - 0.5, exclude=unseen)
        out[f"{name}_blocked"] = np.asarray(blocked, bool)
        out[f"{name}_incidence_deg"] = np.degrees(np.arccos(np.clip(np.abs(
            np.einsum("ij,ij->i", v / dist[:, None], n)), 0, 1)))
    out["left_incidence_deg"] = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", d, n)),
                                                             0, 1)))
    mech = np.full(len(X), "other", object)
    grazing = np.maximum(out["left_incidence_deg"], out["right_incidence_deg"]) > grazing_deg
    for name, mask in (("grazing", grazing), ("shadow", out["projector_blocked"]),
                       ("right_occluded", out["right_blocked"]),
                       ("depth_edge", spread > edge_mm)):
        mech[mask] = name  # the later, the more specific
    out["mechanism"] = mech
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a `scancell demo` run directory (runs/<stamp>)")
    ap.add_argument("--threshold", type=float, default=0.5, help="mm from the true surface")
    ap.add_argument("--edge-mm", type=float, default=2.0,
                    help="a true depth spread within ±2 px beyond this is a depth edge (mm)")
    ap.add_argument("--grazing-deg", type=float, default=75.0)
    ap.add_argument("--json", type=Path, help="write every outlier's record here")
    a = ap.parse_args()
    recording, log, _, cell, offset = simulated_run(a.run)
    T_true_from_cal = np.linalg.inv(offset.T_cal_from_true)
    T_part_from_world = np.linalg.inv(cell.cfg.T_world_from_part)
    poses, _ = recorded_poses(recording)
    records = station_records(recording)
    total, rows, found = 0, [], []
    for st in poses:
        logged = true_pose(log, records[st.scan_id])
        if logged is None:
            continue
        try:
            pts, _ = station_cloud(recording, st)
        except FusionError:
            continue
        T_cam = np.asarray(logged["T_world_from_mcs"], float)
        X = apply_T(T_cam @ T_true_from_cal, pts.astype(float))
        dist = cell.surface_distance(X)
        bad = np.flatnonzero(dist > a.threshold)
        total += len(pts)
        rows.append((st.name, len(pts), len(bad)))
        if not len(bad):
            continue
        rig_now = cell.rig_at(float(logged["sim_s"]))
        info = classify(cell, rig_now, T_cam, X[bad], a.edge_mm, a.grazing_deg)
        part = apply_T(T_part_from_world, X[bad])
        mechs, counts = np.unique(info["mechanism"], return_counts=True)
        print(f"{st.name}: {len(bad)} of {len(pts)} points beyond {a.threshold} mm "
              f"(max {dist[bad].max():.2f} mm); part frame x {np.median(part[:, 0]):.0f}, "
              f"y {part[:, 1].min():.0f}..{part[:, 1].max():.0f}, z {np.median(part[:, 2]):.0f}; "
              + ", ".join(f"{m} {c}" for m, c in zip(mechs, counts, strict=True))
              + f"; error along the ray median {np.median(info['error_along_ray_mm']):+.2f} mm, "
                f"depth spread median {np.median(info['depth_spread_mm']):.1f} mm, incidence "
                f"left/right median {np.median(info['left_incidence_deg']):.0f}/"
                f"{np.median(info['right_incidence_deg']):.0f} deg; left image u "
                f"{np.percentile(info['left_u_px'], 5):.0f}..{np.percentile(info['left_u_px'], 95):.0f}"
                f", v {np.percentile(info['left_v_px'], 5):.0f}..{np.percentile(info['left_v_px'], 95):.0f}"
                f" of {rig_now.left.width} x {rig_now.left.height} px")
        for k in range(len(bad)):
            found.append({"station": st.name, "index": int(bad[k]), "distance_mm": float(dist[bad[k]]),
                          "part_mm": part[k].round(3).tolist(),
                          **{key: (v[k].item() if hasattr(v[k], "item") else v[k])
                             for key, v in info.items()}})
    n_bad = sum(r[2] for r in rows)
    print(f"all stations: {n_bad} of {total} points beyond {a.threshold} mm ({n_bad / max(total, 1):.2e})")
    if found:
        mechs, counts = np.unique([f["mechanism"] for f in found], return_counts=True)
        print("by mechanism: " + ", ".join(f"{m} {c}" for m, c in zip(mechs, counts, strict=True)))
    if a.json:
        a.json.write_text(json.dumps(found))
    return 0


if __name__ == "__main__":
    sys.exit(main())
