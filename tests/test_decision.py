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
