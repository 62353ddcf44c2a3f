"""Verdicts that account for the uncertainty (ISO 14253-1 guard bands, analysis/decision.py):
single values, surface regions judged point by point, defects by their robust height, and the
bad input around them."""

from __future__ import annotations

import numpy as np
import pytest
from scancell.analysis import decision
from scancell.analysis.tolerance import Tolerance, defect_height, judge
from scancell.analysis.uncertainty import PointUncertaintyError, check_point_sigma

pytestmark = pytest.mark.unit

ZONE = decision.Zone(-0.3, 0.3)


@pytest.mark.parametrize(("value", "U", "rule", "verdict"), [
    (0.20, 0.05, "iso14253-1", "pass"),      # inside the zone less U
    (0.27, 0.05, "iso14253-1", "not provable"),  # inside, but within U of the edge
    (0.33, 0.05, "iso14253-1", "not provable"),  # outside, but within U of the edge
    (0.36, 0.05, "iso14253-1", "fail"),      # beyond the zone plus U
    (-0.36, 0.05, "iso14253-1", "fail"),
    (0.27, 0.05, "simple", "pass"),          # the edge alone decides
    (0.33, 0.05, "simple", "fail"),
    (float("nan"), 0.05, "iso14253-1", "not measured"),
])
def test_a_value_is_decided_by_the_guard_bands(value, U, rule, verdict):
    assert decision.decide(value, U, ZONE, rule) == verdict


def test_unknown_rules_and_bad_uncertainties_are_refused():
    with pytest.raises(decision.DecisionError, match="iso14253-1, simple"):
        decision.decide(0.1, 0.05, ZONE, "lenient")
    with pytest.raises(decision.DecisionError, match="finite number >= 0"):
        decision.decide(0.1, -0.01, ZONE)


def test_verdicts_combine_and_a_boolean_pass_means_proven():
    assert decision.combine(["pass", "pass", "not measured"]) == "pass"
    assert decision.combine(["pass", "not provable"]) == "not provable"
    assert decision.combine(["not provable", "fail"]) == "fail"
    assert decision.combine(["not measured"]) == "not measured"
    assert [decision.as_pass(v) for v in decision.VERDICTS] == [True, False, False, None]


def plate(bump_mm: float, sigma_mm: float = 0.02, spacing: float = 0.5, seed: int = 1):
    """A 60 x 60 mm patch of points (part frame, mm) on a grid, each deviation a Gaussian bump
    of height ``bump_mm`` (sigma 6 mm) at the centre plus noise of ``sigma_mm``."""
    g = np.arange(-30, 30, spacing)
    X, Y = np.meshgrid(g, g)
    pts = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    truth = bump_mm * np.exp(-(X.ravel() ** 2 + Y.ravel() ** 2) / (2 * 6.0 ** 2))
    rng = np.random.default_rng(seed)
    dev = truth + rng.normal(0, sigma_mm, len(pts))
    return pts, dev.astype(np.float32), np.full(len(pts), sigma_mm, np.float32)


def test_a_defect_is_reported_by_its_robust_height_within_0_06_mm_of_the_truth():
    pts, dev, sigma = plate(0.6)
    r = judge(dev, Tolerance(-0.3, 0.3), 0.01, pts, 0.5, 25.0, None, sigma)
    (d,) = r["defects"]
    assert abs(d["height_mm"] - 0.6) <= 0.06
    assert d["extreme_mm"] > d["height_mm"]  # the noisiest point overstates it
    assert 0 < d["U_mm"] < 0.05
    assert d["verdict"] == "fail" and r["verdict"] == "fail" and r["pass"] is False


def test_a_defect_within_its_uncertainty_of_the_limit_is_not_provable():
    # noise 0.05 mm with a common (pose) share the scatter does not show: stated 0.08 mm
    pts, dev, _ = plate(0.33, sigma_mm=0.05)
    stated = np.full(len(dev), 0.08, np.float32)
    r = judge(dev, Tolerance(-0.3, 0.3), 0.05, pts, 0.5, 25.0, None, stated)
    assert r["defects"], "the bump's noisy top makes a patch beyond +0.3"
    d = r["defects"][0]
    assert d["U_mm"] > abs(d["height_mm"] - 0.3)
    assert d["verdict"] == "not provable"
    assert r["verdict"] == "not provable" and r["pass"] is False
    simple = judge(dev, Tolerance(-0.3, 0.3), 0.05, pts, 0.5, 25.0, None, stated, "simple")
    assert simple["verdict"] == "fail"


def test_a_perfect_part_passes_and_a_noise_patch_is_no_defect():
    pts, dev, sigma = plate(0.0, sigma_mm=0.02)
    dev[:40] = 0.35  # one stray row of points beyond the zone: 10 mm², under the defect area
    r = judge(dev, Tolerance(-0.3, 0.3), 0.01, pts, 0.5, 25.0, None, sigma)
    assert r["verdict"] == "pass" and r["pass"] is True
    assert r["U_mm"] == pytest.approx(0.04, abs=1e-6)


def test_a_tolerance_narrower_than_U_is_not_provable_everywhere_and_says_why():
    pts, dev, sigma = plate(0.0, sigma_mm=0.02)
    r = judge(dev, Tolerance(-0.03, 0.03), 0.01, pts, 0.5, 25.0, None, sigma * 2)
    assert r["verdict"] == "not provable"
    assert r["proven_inside_share"] == 0.0
    assert "no wider than twice" in r["note"] and "U = 0.080 mm" in r["note"]


def test_a_region_without_points_is_not_measured():
    r = judge(np.zeros(0, np.float32), Tolerance(-0.3, 0.3), 0.01)
    assert r["verdict"] == "not measured" and r["pass"] is None


def test_the_height_uses_the_neighbours_not_the_patch_alone():
    pts, dev, sigma = plate(0.6)
    patch = pts[dev > 0.3]
    h, u = defect_height(pts, dev, None, sigma, patch, "above", 0.5)
    assert abs(h - 0.6) < 0.06 and u > 0


def test_point_uncertainties_with_nan_or_negative_values_are_refused_naming_where():
    s = np.array([0.01, 0.02, np.nan, -0.1, 0.01])
    with pytest.raises(PointUncertaintyError, match=r"2 point uncertainties .* index 2"):
        check_point_sigma(s, 5, "cloud.ply")
    with pytest.raises(PointUncertaintyError, match="4 uncertainties for 5 points"):
        check_point_sigma(s[:4], 5, "cloud.ply")


def box_part(tmp_path, sigma_mm: float | None, bump_mm: float = 0.0, bad: bool = False):
    """A 200 x 200 x 40 mm box's STL and a scan of its top face (z = 40) as a PLY, with a
    Gaussian bump of ``bump_mm`` (sigma 6 mm) at its centre, noise 0.02 mm and, unless
    ``sigma_mm`` is None, an ``uncertainty`` property (with NaN and a negative if ``bad``)."""
    import open3d as o3d
    from scancell.analysis.cloud_io import write_ply

    box = o3d.geometry.TriangleMesh.create_box(200.0, 200.0, 40.0)
    box.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(tmp_path / "box.stl"), box)
    g = np.arange(5.0, 195.0, 0.5)
    X, Y = np.meshgrid(g, g)
    rng = np.random.default_rng(3)
    z = 40.0 + bump_mm * np.exp(-((X - 100) ** 2 + (Y - 100) ** 2) / 72.0) \
        + rng.normal(0, 0.02, X.shape)
    pts = np.stack([X.ravel(), Y.ravel(), z.ravel()], axis=1)
    fields = None
    if sigma_mm is not None:
        s = np.full(len(pts), sigma_mm)
        if bad:
            s[[7, 9]] = [np.nan, -0.01]
        fields = {"uncertainty": s.astype(np.float32)}
    write_ply(tmp_path / "scan.ply", pts, fields)
    return tmp_path / "scan.ply", tmp_path / "box.stl"


def inspect_cli(tmp_path, measured, nominal, *args):
    import json

    from scancell.cli import main as cli_main

    out = tmp_path / "out.json"
    code = cli_main(["inspect", str(measured), "--nominal", str(nominal), "--align",
                     "asmeasured", "--transform", ",".join(map(str, np.eye(4).ravel())),
                     "--tolerance", "0.3", "--json", str(out), "--report",
                     str(tmp_path / "report"), *args])
    return code, (json.loads(out.read_text()) if out.exists() else None)


def test_a_cloud_with_its_uncertainty_is_judged_by_it_through_the_cli(tmp_path, capsys):
    measured, nominal = box_part(tmp_path, 0.03, bump_mm=0.6)
    code, body = inspect_cli(tmp_path, measured, nominal)
    t = body["tolerances"]
    assert code == 1 and t["verdict"] == "fail" and t["pass"] is False
    assert body["uncertainty"]["source"] == "points"
    (d,) = t["overall"]["defects"]
    assert abs(d["height_mm"] - 0.6) < 0.06 and d["verdict"] == "fail"
    html = (tmp_path / "report" / "report.html").read_text()
    assert "Decision rule: ISO 14253-1" in html and "FAIL" in html
    assert "verdict: FAIL" in capsys.readouterr().out


def test_a_cloud_without_uncertainty_is_judged_with_a_stated_default_and_says_so(tmp_path):
    measured, nominal = box_part(tmp_path, None)
    code, body = inspect_cli(tmp_path, measured, nominal)
    assert code == 0 and body["tolerances"]["verdict"] == "pass"
    u = body["uncertainty"]
    assert u["source"] == "scatter" and u["median_sigma_mm"] == pytest.approx(0.02, rel=0.25)
    assert "carries no per-point uncertainty" in u["note"]
    assert "carries no per-point uncertainty" in (tmp_path / "report" / "report.html").read_text()
    code, body = inspect_cli(tmp_path, measured, nominal, "--point-sigma", "0.2")
    assert code == 4 and body["tolerances"]["verdict"] == "not provable"  # U = 0.4 > 0.3
    assert "no wider than twice" in body["tolerances"]["overall"]["note"]
    code, body = inspect_cli(tmp_path, measured, nominal, "--point-sigma", "0.2",
                             "--decision-rule", "simple")
    assert code == 0 and body["tolerances"]["verdict"] == "pass"


def test_nan_or_negative_uncertainties_are_refused_and_nothing_is_written(tmp_path, capsys):
    measured, nominal = box_part(tmp_path, 0.03, bad=True)
    code, body = inspect_cli(tmp_path, measured, nominal)
    assert code == 2 and body is None and not (tmp_path / "report").exists()
    err = capsys.readouterr().err
    assert "2 point uncertainties are NaN, infinite or negative (the first at index 7" in err
