"""Speed and accuracy of `scancell inspect` (issue 20): 3 M measured points against a
500 k-triangle nominal, beside CloudCompare's cloud-to-mesh distance on the same files, in the
same run.

- The nominal: the simulated car rear as an STL of ~500 k triangles (1.67 mm facets).
- The measured cloud: 3 M points of the car rear with a 0.5 mm dent and its right flank 0.6 mm
  out (sim.parts), 0.015 mm noise, moved by a few mm and degrees.
- scancell: (1) the signed deviation alone (the cloud already aligned: what C2M does), (2) the
  whole `scancell inspect --align bestfit --out-ply --json` as a process (read, align, deviation,
  tolerances, coverage, sections, PLY), (3) the same with the HTML report.
- CloudCompare 2.x, headless: (1) `-C2M_DIST` on the aligned cloud; (2) `-ICP` then
  `-C2M_DIST` on the moved cloud (its own alignment and distances).
- Accuracy against the truth: the dent's and the flange's depth, the mean elsewhere.

Run: .venv/bin/python benchmarks/bench_inspect.py  (or `make bench`); ``--points 50e6`` for the
large-part figure of issue 37 (a 50 M-point cloud: ≤ 3 GB, ≤ 1.2 x CloudCompare's time).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d
from cloudcompare import run_cloudcompare
from scancell.analysis.alignment import apply
from scancell.analysis.cloud_io import read_ply, write_ply
from scancell.analysis.deviation import closest_points
from scancell.analysis.nominal import load_nominal
from scancell.sim import parts
from scipy.spatial.transform import Rotation

N_POINTS = 3_000_000
FACET_MM = 1.67  # ~500 k triangles


def cloudcompare(args: list[str], cwd: Path) -> float | None:
    return run_cloudcompare(["-AUTO_SAVE", "OFF", *args], cwd)


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=N_POINTS, help="measured points (default 3e6)")
    n_points = int(ap.parse_args().points)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        mesh = parts.car_rear(FACET_MM)
        o3d.io.write_triangle_mesh(str(tmp / "nominal.stl"), mesh)
        o3d.utility.random.seed(5)
        defect = parts.car_rear_defects(defects=("dent", "flange"))
        truth = np.asarray(defect.sample_points_uniformly(n_points).points)
        truth += np.random.default_rng(5).normal(0, 0.015, truth.shape)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", [1.5, -2.0, 2.5], degrees=True).as_matrix()
        T[:3, 3] = [4.0, -3.0, 2.0]
        write_ply(tmp / "aligned.ply", truth)
        write_ply(tmp / "moved.ply", apply(T, truth))
        print(f"nominal {len(mesh.triangles)} triangles; measured {n_points} points")

        t0 = time.perf_counter()
        nominal = load_nominal(tmp / "nominal.stl")
        pts, _ = read_ply(tmp / "aligned.ply")
        dev = closest_points(nominal, pts).deviation
        t_dev = time.perf_counter() - t0
        t_cc = cloudcompare(["-O", "aligned.ply", "-O", "nominal.stl", "-C2M_DIST"], tmp)
        print(f"signed deviation (read files, closest points, sign): {t_dev:.1f} s"
              + (f"; CloudCompare -C2M_DIST {t_cc:.1f} s; ratio {t_dev / t_cc:.2f}" if t_cc else ""))

        runs, peaks = {}, {}
        for name, extra in (("inspect", []), ("inspect + HTML report", ["--report", str(tmp / "r")])):
            t0 = time.perf_counter()
            p = subprocess.Popen([sys.executable, "-m", "scancell", "inspect",
                                  str(tmp / "moved.ply"), "--nominal", str(tmp / "nominal.stl"),
                                  "--align", "bestfit", "--out-ply", str(tmp / "out.ply"),
                                  "--json", str(tmp / "o.json"), "--tolerance", "0.3", *extra],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            _, status, usage = os.wait4(p.pid, 0)  # this process's own peak RSS
            runs[name] = time.perf_counter() - t0
            peaks[name] = usage.ru_maxrss / 1024
            if os.waitstatus_to_exitcode(status) not in (0, 1):
                print(p.stderr.read().decode()[-1000:])
                return
        # CloudCompare's ICP on 3 M points took 98 s: on a large cloud only its C2M is run
        t_icp = (cloudcompare(["-O", "moved.ply", "-O", "nominal.stl", "-ICP",
                               "-RANDOM_SAMPLING_LIMIT", "200000", "-C2M_DIST"], tmp)
                 if n_points <= N_POINTS else None)
        import json

        parts_s = json.loads((tmp / "o.json").read_text())["seconds"]
        print(f"inside scancell inspect (s): {parts_s}")
        for name, t in runs.items():
            print(f"scancell {name} (bestfit, deviation, tolerances, coverage, sections, PLY): "
                  f"{t:.1f} s, peak RSS {peaks[name]:.0f} MB ({peaks[name] * 2**20 / n_points:.0f} "
                  f"bytes a point)" + (f"; CloudCompare -ICP -C2M_DIST {t_icp:.1f} s; ratio "
                                       f"{t / t_icp:.2f}" if t_icp else ""))
        out = o3d.t.io.read_point_cloud(str(tmp / "out.ply")).point["deviation"].numpy().ravel()
        y, z = truth[:, 1], truth[:, 2]
        for d in parts.car_rear_defects_truth(("dent", "flange")):
            near = np.hypot(y - d.at_mm[1], z - d.at_mm[2]) < 2
            print(f"  {d.name}: true {d.deviation_mm:+.4f} mm, inspected {out[near].mean():+.4f} mm")
        elsewhere = (np.hypot(y - parts.DENT_YZ[0], z - parts.DENT_YZ[1]) > 100) & (y < 540)
        print(f"  mean elsewhere {out[elsewhere].mean():+.5f} mm (truth 0); deviation-only run "
              f"mean elsewhere {dev[elsewhere].mean():+.5f} mm")


if __name__ == "__main__":
    main()
