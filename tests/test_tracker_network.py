"""The tracker-station bundle (analysis/tracker_network.py, issue 19): over seeded draws the
stations' errors against the truth lie within their reported covariance; too few or collinear
common nests are refused naming the station; a knocked nest stands out by name."""

from __future__ import annotations

import numpy as np
import pytest
from scancell.analysis.tracker_network import (
    NetworkError,
    TrackerSigma,
    pose_error,
    solve_network,
)
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

SIGMA = TrackerSigma()
#: reference nests around a car body's cell (world = the first tracker station's frame, mm)
NESTS = {f"N{i}": np.array(p, float) for i, p in enumerate([
    (3000, -2200, 0), (5500, -2100, 900), (6500, 0, 200), (5600, 2200, 1200),
    (3000, 2300, 100), (1500, 1800, 1500), (1200, -1700, 700), (4200, 0, 1600)])}


def station(yaw_deg: float, tilt_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zx", [yaw_deg, tilt_deg], degrees=True).as_matrix()
    T[:3, 3] = t
    return T


TRUTH = {"T0": np.eye(4), "T1": station(150.0, 0.5, (8200.0, 600.0, -50.0)),
         "T2": station(-80.0, -0.3, (4300.0, 4300.0, 30.0))}


def measure(rng: np.random.Generator, nests=NESTS, truth=TRUTH, seen=None):
    out = {}
    for s, T in truth.items():
        out[s] = {}
        for n, X in nests.items():
            if seen is not None and n not in seen[s]:
                continue
            m = T[:3, :3].T @ (X - T[:3, 3])
            rng_mm = np.linalg.norm(m)
            u = m / rng_mm
            s_r, s_t = SIGMA.sigmas_mm(rng_mm)
            a, b = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2].T
            out[s][n] = m + u * rng.normal(0, s_r) + a * rng.normal(0, s_t) + b * rng.normal(0, s_t)
    return out


@pytest.mark.unit
def test_station_errors_lie_within_the_reported_covariance_over_60_draws():
    d2, nest_d2, vf = [], [], []
    for seed in range(60):
        sol = solve_network(measure(np.random.default_rng(seed)), SIGMA, ["T0", "T1", "T2"])
        assert np.allclose(sol.stations["T0"], np.eye(4))
        for s in ("T1", "T2"):
            e = pose_error(sol.stations[s], TRUTH[s])
            d2.append(e @ np.linalg.solve(sol.station_cov[s], e))
        for n, X in NESTS.items():
            e = sol.nests[n] - X
            nest_d2.append(e @ np.linalg.solve(sol.nest_cov[n], e))
        vf.append(sol.variance_factor)
    d2, nest_d2 = np.array(d2), np.array(nest_d2)
    inside = np.mean(d2 < chi2.ppf(0.95, 6))
    assert inside >= 0.90, (inside, np.sort(d2)[-10:])
    assert 4.5 < d2.mean() < 7.5, d2.mean()  # chi-squared with 6 degrees of freedom
    assert np.mean(nest_d2 < chi2.ppf(0.95, 3)) >= 0.90 and 2.2 < nest_d2.mean() < 3.8
    assert 0.7 < np.mean(vf) < 1.3  # the sigmas describe the noise
    one = solve_network(measure(np.random.default_rng(0)), SIGMA, ["T0", "T1", "T2"])
    sig = one.station_sigma("T1")
    assert 0.002 < sig["translation_mm"] < 0.1 and 0.05 < sig["rotation_arcsec"] < 5.0


@pytest.mark.unit
def test_a_station_without_three_common_nests_or_with_collinear_ones_is_refused():
    rng = np.random.default_rng(1)
    seen = {"T0": set(NESTS), "T1": {"N2", "N3", "N9"}, "T2": set(NESTS)}
    with pytest.raises(NetworkError, match=r"station T1 sees 2 nest\(s\).*N2, N3.*at least 3"):
        solve_network(measure(rng, seen=seen), SIGMA, ["T0", "T1", "T2"])
    line = {f"L{i}": np.array([2000.0 + 500 * i, 0.0, 300.0]) for i in range(4)}
    with pytest.raises(NetworkError, match="station T1: its common nests L0, L1, L2, L3 lie on a"):
        solve_network(measure(rng, nests=line, truth={k: TRUTH[k] for k in ("T0", "T1")}),
                      SIGMA, ["T0", "T1"])


@pytest.mark.unit
def test_a_knocked_nest_stands_out_by_name():
    m = measure(np.random.default_rng(2))
    m["T2"]["N5"] = m["T2"]["N5"] + np.array([0.0, 0.3, 0.0])  # knocked between T1 and T2
    sol = solve_network(m, SIGMA, ["T0", "T1", "T2"])
    (st, nest), sigmas = sol.worst()
    assert (st, nest) == ("T2", "N5") and sigmas > 5.0
    assert sol.variance_factor > 3.0
