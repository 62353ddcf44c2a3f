"""Rendering one full-size camera image set at a new pose: geometry + 9 shaded patterns.

Reference, measured in the same run: the same 9 images rendered without reuse, i.e. one full
geometry pass (ray cast, projector mapping, shadow test) per pattern, as a renderer that treats
each pattern as a new frame would do.

Run: .venv/bin/python benchmarks/bench_render.py  (or `make bench`)
"""

from __future__ import annotations

import time

import numpy as np
from scancell.sim.cell import SimCell, SimCellConfig


def main() -> dict[str, float]:
    cell = SimCell(SimCellConfig(camera_scale=1, seed=0))
    centre = cell.cfg.T_world_from_part[:3, 3]
    targets = [centre + np.array(d) for d in ([0.0, 0, 0], [50.0, -300, -100], [0.0, 250, 50])]
    poses = [cell.ik_for_mcs(cell.mcs_pose_looking_at(t)) for t in targets]
    cell.move_joints(poses[0])
    t0 = time.perf_counter()
    cell.geometry("left")  # one-off: per-pixel ray directions are cached per camera
    t_rays_once = time.perf_counter() - t0

    cell.move_joints(poses[1])
    t0 = time.perf_counter()
    g = cell.geometry("left")
    t_geom = time.perf_counter() - t0
    split = dict(cell.timings)
    t0 = time.perf_counter()
    imgs = [cell.render("left", k) for k in range(9)]
    t_shade9 = time.perf_counter() - t0
    t_new_pose = t_geom + t_shade9

    # reference: no reuse of the ray cast between patterns
    cell.move_joints(poses[2])
    t0 = time.perf_counter()
    for k in range(9):
        cell._geom_cache.clear()
        cell.render("left", k)
    t_ref = time.perf_counter() - t0

    h, w = imgs[0].shape
    print(f"camera {w} x {h}, {g.hit.mean():.0%} of pixels hit, "
          f"{np.isfinite(g.proj_x).mean():.0%} lit")
    print(f"one-off per-camera pixel rays (cached):      {t_rays_once:6.2f} s")
    print("geometry at a new pose:                      "
          f"{t_geom:6.2f} s  (" + ", ".join(f"{k} {v:.2f}" for k, v in split.items()) + ")")
    print(f"9 patterns shaded + blur + noise + quantise: {t_shade9:6.2f} s "
          f"({t_shade9 / 9:.3f} s each)")
    print(f"new pose, 9 images (one ray cast):           {t_new_pose:6.2f} s")
    print(f"reference, 9 images with 9 ray casts:        {t_ref:6.2f} s")
    print(f"ratio scancell / reference:                  {t_new_pose / t_ref:6.2f}")
    return {"new_pose_s": t_new_pose, "reference_s": t_ref, "geometry_s": t_geom,
            "shade9_s": t_shade9}


if __name__ == "__main__":
    main()
