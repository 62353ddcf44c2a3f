"""Free-space consistency (analysis/free_space.py): a point one station places in the space
another station saw through is left out; a point on a surface, beside a depth edge whose near
pixels the decoder dropped, or hidden from the other station, is kept."""

from __future__ import annotations

import numpy as np
import pytest
from scancell.analysis.free_space import DepthView, FreeSpace
from scancell.model.transforms import make_T

pytestmark = pytest.mark.unit


def camera_looking(at: np.ndarray, from_: np.ndarray) -> np.ndarray:
    """T_world_from_mcs of a camera at ``from_`` whose optical axis (z) points at ``at``."""
    z = (at - from_) / np.linalg.norm(at - from_)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    return make_T(np.stack([x, np.cross(z, x), z], axis=1), from_)


def scan(T_world_from_mcs: np.ndarray, surface, pixels: int = 400, fov: float = 0.3,
         noise: float = 0.02, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A station's cloud (MCS, mm) of ``surface``: its pixel rays' hits (``surface(origin,
    dirs)`` -> depth along each ray, NaN for none), with depth noise."""
    u = np.linspace(-fov / 2, fov / 2, pixels)
    U, V = np.meshgrid(u, u)
    d = np.stack([U.ravel(), V.ravel(), np.ones(U.size)], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    R, t = T_world_from_mcs[:3, :3], T_world_from_mcs[:3, 3]
    depth = surface(t, d @ R.T)
    ok = np.isfinite(depth)
    pts = d[ok] * depth[ok, None]
    rng = np.random.default_rng(seed)
    pts = pts + pts / pts[:, 2:] * rng.normal(0, noise, (len(pts), 1))
    return pts, np.full(len(pts), noise)


def step_surface(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """The plane z = 0 for x < 0 and a step up to z = 12 for x >= 0 (world, mm): the range
    along each ray from ``origin`` to the first of them it meets."""
    t_low = (0.0 - origin[2]) / dirs[:, 2]
    t_high = (12.0 - origin[2]) / dirs[:, 2]
    x_high = origin[0] + t_high * dirs[:, 0]
    x_low = origin[0] + t_low * dirs[:, 0]
    t = np.where(x_high >= 0, t_high, np.where(x_low < 0, t_low, np.nan))
    return np.where(t > 0, t, np.nan)


def world(pts: np.ndarray, T: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


def test_points_another_station_saw_through_are_left_out_and_the_surface_kept():
    A = camera_looking(np.array([0.0, 0, 0]), np.array([-150.0, 0, 650]))
    B = camera_looking(np.array([0.0, 0, 0]), np.array([200.0, 50, 620]))
    pa, sa = scan(A, step_surface)
    pb, sb = scan(B, step_surface, seed=1)
    # A's stereo match across an occlusion: a strip of its points 3 mm in front of the surface
    wrong = (pa[:, 0] > 20) & (pa[:, 0] < 30)
    pa_bad = pa.copy()
    pa_bad[wrong] *= 1 - 3.0 / pa_bad[wrong, 2:]
    fs = FreeSpace()
    fs.add(DepthView.of("A", pa_bad, A, sa, 0.02))
    fs.add(DepthView.of("B", pb, B, sb, 0.02))
    X = np.concatenate([world(pa_bad, A), world(pb, B)])
    sigma = np.full(len(X), np.hypot(0.02, 0.02))
    out = fs.contradicted(X, sigma)
    truth = np.r_[wrong, np.zeros(len(pb), bool)]
    assert out[truth].mean() > 0.95, "B saw through A's strip"
    assert not out[~truth].any(), "no point on the surface is left out"
    assert fs.to_json()["by_station"] == {"B": int(out.sum())}
    kept, _ = next(iter(fs.keep([(X, sigma)])))
    assert len(kept) == len(X) - out.sum()


def test_a_depth_edge_whose_near_pixels_were_dropped_contradicts_nothing():
    # B's view over the step's edge: the decoder leaves out its pixels next to the jump, so
    # its cells there hold only the low floor, 12 mm behind the step's edge
    A = camera_looking(np.array([0.0, 0, 6]), np.array([-300.0, 0, 600]))
    B = camera_looking(np.array([0.0, 0, 0]), np.array([250.0, 0, 600]))
    pa, _ = scan(A, step_surface)
    pb, sb = scan(B, step_surface, seed=1)
    wb = world(pb, B)
    near_edge = np.abs(wb[:, 0]) < 2.0
    fs = FreeSpace()
    fs.add(DepthView.of("B", pb[~near_edge], B, sb[~near_edge], 0.02))
    assert not fs.contradicted(world(pa, A), np.full(len(pa), 0.03)).any()


def test_points_hidden_from_a_station_are_not_judged_by_it():
    # a point behind the surface B sees (B cannot see it): never seen through
    B = camera_looking(np.array([0.0, 0, 0]), np.array([0.0, 0, 650]))
    pb, sb = scan(B, step_surface)
    fs = FreeSpace()
    fs.add(DepthView.of("B", pb, B, sb, 0.02))
    behind = np.array([[-50.0, 0.0, -4.0], [60.0, 0.0, 5.0]])
    assert not fs.contradicted(behind, np.full(2, 0.03)).any()
    empty = DepthView.of("E", np.zeros((0, 3)), B, 0.02, 0.0)
    assert not empty.saw_through(behind, np.full(2, 0.03)).any()


def test_the_threshold_is_six_combined_sigmas():
    B = camera_looking(np.array([-100.0, 0, 0]), np.array([-100.0, 0, 650]))
    pb, _ = scan(B, step_surface, noise=0.0)
    fs = FreeSpace()
    fs.add(DepthView.of("B", pb, B, 0.05, 0.0))
    above = np.array([[-100.0, 0.0, 0.29], [-100.0, 0.0, 0.32]])  # 6 x hypot(0.05, 0.01) = 0.306
    assert fs.contradicted(above, np.full(2, 0.01)).tolist() == [False, True]
