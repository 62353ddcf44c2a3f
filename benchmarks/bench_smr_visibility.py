"""Where the tracker can fix the scanner's pose: the paper's one rear SMR against an SMR cluster
on the housing (issue 19).

Views: every candidate view the planner makes of the simulated car rear (surface patches one
field step apart, each looked at along its normal and tilted 20 deg four ways) that the robot
reaches inside its joint limits from the rail position nearest it. For each view the bench
counts the SMRs the tracker at the cell's origin sees: inside the SMR's +/-30 deg acceptance
and no part in the beam (the planner's own checks). A view counts as fixed when the single SMR
is seen at the view and at both J6 turns (the paper's method), or when >= 3 SMRs of the cluster
are seen at once; with "roll", each view may turn J6 in 30 deg steps to bring a face round.

Reference, same run: the single rear SMR. Figures: the share of views each fixes.

Run: .venv/bin/python benchmarks/bench_smr_visibility.py  (or `make bench`)
"""

from __future__ import annotations

import time

import numpy as np
import open3d as o3d
from scancell.analysis.planner import Planner, _tilted
from scancell.model.cell_geometry import CellGeometry
from scancell.model.robot_model import IKError
from scancell.model.transforms import T_rot_z, look_at_flange
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.parts import HOUSING_SMR_CLUSTER

ROLLS_DEG = range(0, 360, 30)


def reachable_views(pl: Planner, g: CellGeometry) -> list[np.ndarray]:
    step = 0.75 * min(g.field_mm)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pl.points))
    pcd.normals = o3d.utility.Vector3dVector(pl.normals)
    patches = pcd.voxel_down_sample(step / 2)
    out = []
    for c, n in zip(np.asarray(patches.points), np.asarray(patches.normals), strict=True):
        for view in _tilted(-n / np.linalg.norm(n), 20.0):
            T = look_at_flange(c, view, g.standoff_mm, g.rig_mid_in_flange)
            if pl.seen(T).sum() < 20:
                continue
            for rail in g.rail_nearest(c):
                Tb = np.linalg.inv(g.base_at(rail)) @ T
                if not g.robot.within_reach(Tb):
                    continue
                try:
                    q = g.robot.ik(Tb, None)
                except IKError:
                    continue
                if g.robot.within_limits(q):
                    out.append(T)
                    break
    return out


def seen(pl: Planner, g: CellGeometry, T_world_from_flange: np.ndarray,
         smrs: dict[str, tuple]) -> int:
    T = T_world_from_flange @ g.T_flange_from_mcs
    k = 0
    for centre, opening in smrs.values():
        p = T[:3, :3] @ np.asarray(centre, float) + T[:3, 3]
        to = g.tracker_world_mm - p
        o = T[:3, :3] @ (np.asarray(opening, float) / np.linalg.norm(opening))
        if o @ to / np.linalg.norm(to) < np.cos(np.radians(g.smr_acceptance_deg)):
            continue
        k += bool(pl._clear(p[None] + 25.0 * to[None] / np.linalg.norm(to),
                            g.tracker_world_mm[None])[0])
    return k


def main() -> dict[str, float]:
    t0 = time.perf_counter()
    cell = SimCell(SimCellConfig(camera_scale=16))
    g = CellGeometry.from_table(cell.planner_table())
    pl = Planner(cell.part_mesh_world(), g, samples=6000)
    views = reachable_views(pl, g)
    single = {"rear": (g.smr_in_mcs_mm, g.smr_opening_in_mcs)}
    j6 = np.mean([all(seen(pl, g, T @ T_rot_z(a), single) for a in (0.0, *g.j6_angles_deg))
                  for T in views])
    j6_either = np.mean([any(all(seen(pl, g, T @ T_rot_z(s * a), single)
                                 for a in (0.0, *g.j6_angles_deg)) for s in (1.0, -1.0))
                         for T in views])
    cluster = np.mean([seen(pl, g, T, HOUSING_SMR_CLUSTER) >= 3 for T in views])
    rolled = np.mean([max(seen(pl, g, T @ T_rot_z(r), HOUSING_SMR_CLUSTER) for r in ROLLS_DEG)
                      >= 3 for T in views])
    print(f"{len(views)} reachable views of the car rear ({time.perf_counter() - t0:.0f} s)")
    print(f"one rear SMR, J6 turns one way  : {j6:.2f} of the views (reference)")
    print(f"one rear SMR, J6 turns either way: {j6_either:.2f}")
    print(f"cluster ({len(HOUSING_SMR_CLUSTER)} SMRs), >= 3 seen     : {cluster:.2f}  "
          f"ratio {cluster / max(j6_either, 1e-9):.1f}")
    print(f"cluster, J6 roll per view        : {rolled:.2f}  "
          f"ratio {rolled / max(j6_either, 1e-9):.1f} (roll inside the joint limits not checked)")
    return {"views": len(views), "single_j6": float(j6_either), "cluster": float(cluster),
            "cluster_roll": float(rolled)}


if __name__ == "__main__":
    main()
