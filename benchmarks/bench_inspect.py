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

``--part car_body`` (issue 37): the nominal is the car body's STEP (what the demo inspects;
CloudCompare reads its tessellation as an STL, 1.1 M triangles at 0.01 mm chordal), the cloud is
sampled on every face but the underbody (no cell measures it), with the bonnet 0.6 mm out along
its normal and a 0.5 mm dent in the roof; each point's true deviation is known, so the accuracy
is the inspected minus the true deviation, point by point.

``--cluster`` adds a run with the deviation on a local Dask cluster (``--scheduler local``).

Run: .venv/bin/python benchmarks/bench_inspect.py  (or `make bench`); ``--part car_body --points
50e6`` for the large-part figure of issue 37 (a 50 M-point cloud: ≤ 3 GB, ≤ 1.2 x CloudCompare's
time).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from cloudcompare import run_cloudcompare
from scancell.analysis.alignment import apply
from scancell.analysis.cloud_io import read_ply, write_ply
from scancell.analysis.deviation import closest_points
from scancell.analysis.nominal import Nominal, load_nominal
from scancell.sim import parts
from scipy.spatial.transform import Rotation

N_POINTS = 3_000_000
FACET_MM = 1.67  # ~500 k triangles
#: the car body's defects: the bonnet out along its normal, a Gaussian dent in the roof's middle
BONNET_OUT_MM = 0.6
ROOF_DENT_MM, ROOF_DENT_SIGMA_MM = -0.5, 40.0
NOISE_MM = 0.015


@dataclass
class Case:
    """A nominal, the measured cloud's truth (part frame, mm) and how to score the inspection."""
    nominal: Path  # what scancell inspects
    nominal_mesh: Path  # the same surface as a mesh, for CloudCompare
    triangles: int
    truth: np.ndarray  # (N, 3) the measured points before the transform
    score: Callable[[np.ndarray, np.ndarray], list[str]]  # (inspected, deviation-only) -> lines


def car_rear_case(n_points: int, tmp: Path) -> Case:
    mesh = parts.car_rear(FACET_MM)
    o3d.io.write_triangle_mesh(str(tmp / "nominal.stl"), mesh)
    o3d.utility.random.seed(5)
    defect = parts.car_rear_defects(defects=("dent", "flange"))
    truth = np.asarray(defect.sample_points_uniformly(n_points).points)
    truth += np.random.default_rng(5).normal(0, NOISE_MM, truth.shape)

    def score(out: np.ndarray, dev: np.ndarray) -> list[str]:
        y, z = truth[:, 1], truth[:, 2]
        lines = []
        for d in parts.car_rear_defects_truth(("dent", "flange")):
            near = np.hypot(y - d.at_mm[1], z - d.at_mm[2]) < 2
            lines.append(f"  {d.name}: true {d.deviation_mm:+.4f} mm, inspected "
                         f"{out[near].mean():+.4f} mm")
        elsewhere = (np.hypot(y - parts.DENT_YZ[0], z - parts.DENT_YZ[1]) > 100) & (y < 540)
        lines.append(f"  mean elsewhere {out[elsewhere].mean():+.5f} mm (truth 0); deviation-only "
                     f"run mean elsewhere {dev[elsewhere].mean():+.5f} mm")
        return lines

    return Case(tmp / "nominal.stl", tmp / "nominal.stl", len(mesh.triangles), truth, score)


def sample_surface(nominal: Nominal, faces: np.ndarray, n: int, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform by area on the triangles of the CAD faces ``faces`` (indices into
    ``nominal.face_names``) and the triangle each lies on."""
    v, t = nominal.vertices, nominal.triangles
    pick = np.flatnonzero(np.isin(nominal.face_of_triangle, faces))
    a, b, c = (v[t[pick, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = pick[rng.choice(len(pick), n, p=area / area.sum())]
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    pts = ((1 - r1)[:, None] * v[t[tri, 0]] + (r1 * (1 - r2))[:, None] * v[t[tri, 1]]
           + (r1 * r2)[:, None] * v[t[tri, 2]])
    return pts, tri


def car_body_case(n_points: int, tmp: Path) -> Case:
    from scancell.sim.cad import export_nominal

    files = export_nominal("car_body", tmp)
    nominal = load_nominal(files["step"])
    names = np.array(nominal.face_names)
    rng = np.random.default_rng(5)
    pts, tri = sample_surface(nominal, np.flatnonzero(names != "underbody"), n_points, rng)
    face = names[nominal.face_of_triangle[tri]]
    true = np.where(face == "bonnet", BONNET_OUT_MM, 0.0)
    roof = face == "roof"
    centre = np.array([0.0, pts[roof, 1].mean()])
    r2 = ((pts[:, :2] - centre) ** 2).sum(axis=1)
    true += np.where(roof, ROOF_DENT_MM * np.exp(-r2 / (2 * ROOF_DENT_SIGMA_MM ** 2)), 0.0)
    # each point along its triangle's outward normal: the true signed deviation, then the noise
    pts += (true + rng.normal(0, NOISE_MM, n_points))[:, None] * nominal.triangle_normals[tri]
    del tri

    def score(out: np.ndarray, dev: np.ndarray) -> list[str]:
        dent = roof & (r2 < 5.0 ** 2)
        lines = [f"  bonnet: true {BONNET_OUT_MM:+.4f} mm, inspected "
                 f"{out[face == 'bonnet'].mean():+.4f} mm",
                 f"  roof dent (within 5 mm of its centre): true {true[dent].mean():+.4f} mm, "
                 f"inspected {out[dent].mean():+.4f} mm"]
        for name, d in (("bestfit inspection", out), ("deviation only (aligned)", dev)):
            e = d - true
            lines.append(f"  {name}: inspected - true deviation, every point: mean "
                         f"{e.mean():+.5f} mm, |95th| {np.percentile(np.abs(e), 95):.4f} mm "
                         f"(noise {NOISE_MM} mm)")
        return lines

    return Case(Path(files["step"]), Path(files["stl"]), len(nominal.triangles), pts, score)


CASES = {"car_rear": car_rear_case, "car_body": car_body_case}


#: runs a command and writes its peak RSS (kB) to a file: a child forked from this benchmark
#: would count the benchmark's own resident pages (GBs of truth arrays) in its ru_maxrss
LAUNCHER = ("import os, subprocess, sys; p = subprocess.Popen(sys.argv[2:]); "
            "_, status, usage = os.wait4(p.pid, 0); "
            "open(sys.argv[1], 'w').write(str(usage.ru_maxrss)); "
            "sys.exit(os.waitstatus_to_exitcode(status))")


def run_measured(cmd: list[str], tmp: Path) -> tuple[int, float, float, str]:
    """(exit code, seconds, the command's own peak RSS in MB, its stderr's tail)."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", LAUNCHER, str(tmp / "peak_kb"), *cmd],
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seconds = time.perf_counter() - t0
    return r.returncode, seconds, int((tmp / "peak_kb").read_text()) / 1024, r.stderr[-1000:]


def cloudcompare(args: list[str], cwd: Path) -> float | None:
    return run_cloudcompare(["-AUTO_SAVE", "OFF", *args], cwd)


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=N_POINTS, help="measured points (default 3e6)")
    ap.add_argument("--part", choices=sorted(CASES), default="car_rear",
                    help="the nominal and its defects (default car_rear)")
    ap.add_argument("--cluster", action="store_true",
                    help="also the inspection with its deviation on a local Dask cluster "
                         "(--scheduler local: a worker per core)")
    args = ap.parse_args()
    n_points = int(args.points)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        case = CASES[args.part](n_points, tmp)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", [1.5, -2.0, 2.5], degrees=True).as_matrix()
        T[:3, 3] = [4.0, -3.0, 2.0]
        write_ply(tmp / "aligned.ply", case.truth)
        write_ply(tmp / "moved.ply", apply(T, case.truth))
        print(f"{args.part}: nominal {case.nominal.name} ({case.triangles} triangles); measured "
              f"{n_points} points")

        t0 = time.perf_counter()
        nominal = load_nominal(case.nominal)
        pts, _ = read_ply(tmp / "aligned.ply")
        dev = closest_points(nominal, pts).deviation
        del nominal, pts
        t_dev = time.perf_counter() - t0
        mesh_name = case.nominal_mesh.name
        t_cc = cloudcompare(["-O", "aligned.ply", "-O", mesh_name, "-C2M_DIST"], tmp)
        print(f"signed deviation (read files, closest points, sign): {t_dev:.1f} s"
              + (f"; CloudCompare -C2M_DIST {t_cc:.1f} s; ratio {t_dev / t_cc:.2f}" if t_cc else ""))

        runs, peaks = {}, {}
        variants = [("inspect", []), ("inspect + HTML report", ["--report", str(tmp / "r")])]
        if args.cluster:  # the peak RSS is the driver's; each worker holds a tile and the nominal
            variants.append(("inspect, deviation on a local Dask cluster",
                             ["--scheduler", "local"]))
        for name, extra in variants:
            code, runs[name], peaks[name], err = run_measured(
                [sys.executable, "-m", "scancell", "inspect", str(tmp / "moved.ply"), "--nominal",
                 str(case.nominal), "--align", "bestfit", "--out-ply", str(tmp / "out.ply"),
                 "--json", str(tmp / "o.json"), "--tolerance", "0.3", *extra], tmp)
            if code not in (0, 1):
                print(err)
                return
        # CloudCompare's ICP on 3 M points took 98 s: on a large cloud only its C2M is run
        t_icp = (cloudcompare(["-O", "moved.ply", "-O", mesh_name, "-ICP",
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
        print("\n".join(case.score(out, dev)))


if __name__ == "__main__":
    main()
