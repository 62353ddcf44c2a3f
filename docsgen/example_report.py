"""An inspection report for the manual, made when the site is built: the simulated car rear
with its three known form errors, measured with the scanner's noise, against its STEP."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

#: the simulated scanner's typical depth noise (mm, 1-sigma; docs: Simulation models)
NOISE_MM = 0.02
#: a fixture a few mm and a fraction of a degree off, for the best fit to find
FIXTURE_OFFSET_MM = (1.5, -0.8, 0.6)


def example_report() -> dict[str, bytes]:
    """``pictures/inspection/report.html`` and the report's map and histogram as PNGs."""
    from scancell.analysis.inspection import InspectionSettings, inspect_cloud
    from scancell.analysis.inspection_report import histogram, view_maps, write_report
    from scancell.analysis.nominal import load_nominal
    from scancell.analysis.tolerance import parse_spec
    from scancell.sim import parts
    from scancell.sim.cad import export_nominal

    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        step = export_nominal("car_rear", tmp)["step"]
        nominal = load_nominal(step)
        import open3d as o3d

        o3d.utility.random.seed(0)  # the same points, the same report, every build
        mesh = parts.PARTS["car_rear_defects"]()
        mesh.compute_vertex_normals()
        pts = np.asarray(mesh.sample_points_uniformly(400_000, use_triangle_normal=True).points)
        pts = pts + rng.normal(0, NOISE_MM / np.sqrt(3), pts.shape) + np.asarray(FIXTURE_OFFSET_MM)
        settings = InspectionSettings(align="bestfit",
                                      tolerance=parse_spec({"tolerance_mm": 0.3}))
        inspection = inspect_cloud(pts, nominal, settings)
        files = write_report(inspection, Path(tmp) / "report", "car rear (simulated) against "
                             "car_rear.step", "400 000 points sampled from the simulated part "
                             "with its three form errors, noise 0.02 mm")
        out = {"pictures/inspection/report.html": Path(files["html"]).read_bytes(),
               "pictures/inspection/histogram.png": histogram(inspection)}
        maps = view_maps(inspection)
        if maps:
            out["pictures/inspection/map.png"] = maps[0][1]
    return out
