"""Free-space consistency of a fused model: a point another station saw through is no surface.

A station's scanner measures along every pixel's ray up to the first surface; the space in
front of that surface is empty (the visibility constraint volumetric fusion builds on: Curless
& Levoy, SIGGRAPH 1996; Merrell et al., ICCV 2007, "visibility-based fusion of depth maps").
A point that one station places in the space another station saw through is contradicted, and
fusion leaves it out. It catches every mechanism that puts points in the air in front of the
true surface: a stereo match made across an occlusion (`docs/explanation/outliers.md`), mixed
pixels at depth edges, wrong fringe orders.

Each station leaves a depth view: its points in its own frame (MCS, the left camera's), the
nearest depth in each cell of :data:`CELL_RAD` of view angle (~1 mm at the working distance),
and how many points fell in it. A world point X lands in the cell of station j's view along
j's ray, at depth ``z``. X is contradicted when j measured that cell's nearest surface
farther than X by more than their combined uncertainty:

    zmin_j − z > K_SIGMA · sqrt(σ_X² + σ_j²)

with σ_X the point's stated 1-sigma and σ_j the cell's depth noise (the RMS of its points')
and station j's pose uncertainty. A surface that slopes across a cell keeps its nearest depth there, so a
point of that same surface is never farther from the camera than the cell's nearest point
beyond noise; a point that j could not see (an occluded one) lies behind j's surface, not in
front. The cell's depth is the nearest over it and its eight neighbours, and only a cell whose
nine all hold at least :data:`MIN_CELL_POINTS` points speaks: a lone point can be an outlier
behind the surface, and beside a depth edge the decoder leaves the near surface's pixels out.

K_SIGMA = 6: a Gaussian exceeds 6 sigma once in 1e9 tests; a full-size car rear makes ~1e8
(5 M points, ~20 stations each).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

#: a depth view's cell, as view angle (rad): 8 px of a 16 mm lens on 3.45 µm pixels (f = 4638
#: px), 1.1 mm at 650 mm; the finest spacing of the points it judges
CELL_RAD = 8 / 4638
#: cells with fewer points say nothing
MIN_CELL_POINTS = 3
#: the contradiction's threshold in combined sigmas (see the module doc)
K_SIGMA = 6.0
#: how far in front of a station's measured surface a point is still tested (mm): the points
#: an inspection keeps lie within a few mm of the part (its max_distance, 5 mm by default)
REACH_MM = 10.0


@dataclass
class DepthView:
    """One station's nearest depth per cell of view angle (see the module doc)."""

    name: str
    T_mcs_from_world: np.ndarray  # (4, 4)
    cell0: np.ndarray  # (2,) int: the cell index of zmin[0, 0] (x/z, y/z in CELL_RAD)
    #: (H, W) float32 mm: the nearest depth in the cell and its 8 neighbours; inf: none
    zmin: np.ndarray
    #: (H, W) uint8: 1 where the cell and its 8 neighbours all hold MIN_CELL_POINTS points
    count: np.ndarray
    #: (H, W) float32 mm: the cell's depth 1-sigma (the RMS of its points'), its pose's added
    sigma: np.ndarray
    lo: np.ndarray  # (3,) world bounding box of its points, mm
    hi: np.ndarray

    @classmethod
    def of(cls, name: str, cloud_mcs: np.ndarray, T_world_from_mcs: np.ndarray,
           depth_sigma_mm: np.ndarray | float, pose_sigma_mm: float) -> DepthView:
        """The view of a station's cloud (MCS, mm) placed at ``T_world_from_mcs``, with its
        points' depth noise and its pose's 1-sigma (mm)."""
        p = np.asarray(cloud_mcs, np.float64)
        ahead = p[:, 2] > 0
        p = p[ahead]
        ds = np.broadcast_to(np.asarray(depth_sigma_mm, float), ahead.shape)[ahead]
        T = np.asarray(T_world_from_mcs, float)
        if not len(p):
            return cls(name, np.linalg.inv(T), np.zeros(2, np.int64), np.full((1, 1), np.inf,
                       np.float32), np.zeros((1, 1), np.uint8), np.zeros((1, 1), np.float32),
                       T[:3, 3].copy(), T[:3, 3].copy())
        cells = np.floor(p[:, :2] / p[:, 2:] / CELL_RAD).astype(np.int64)
        c0 = cells.min(axis=0)
        w, h = (cells.max(axis=0) - c0 + 1).tolist()
        flat = (cells[:, 1] - c0[1]) * w + (cells[:, 0] - c0[0])
        zmin = np.full(w * h, np.inf)
        np.minimum.at(zmin, flat, p[:, 2])
        n = np.bincount(flat, minlength=w * h)
        var = np.bincount(flat, weights=np.nan_to_num(ds) ** 2, minlength=w * h) / np.maximum(n, 1)
        sigma = np.sqrt(var + pose_sigma_mm ** 2).astype(np.float32).reshape(h, w)
        world = p @ T[:3, :3].T + T[:3, 3]
        near, full = _neighbourhood(zmin.reshape(h, w), n.reshape(h, w) >= MIN_CELL_POINTS)
        return cls(name, np.linalg.inv(T), c0, near.astype(np.float32), full.astype(np.uint8),
                   sigma, world.min(axis=0), world.max(axis=0))

    def saw_through(self, points: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """Per world point (N, 3, mm) with its 1-sigma (N,): this station saw through it."""
        out = np.zeros(len(points), bool)
        near = np.all((points >= self.lo - REACH_MM) & (points <= self.hi + REACH_MM), axis=1)
        rows = np.flatnonzero(near)
        if not len(rows):
            return out
        T = self.T_mcs_from_world
        x = np.asarray(points[rows], float) @ T[:3, :3].T + T[:3, 3]
        z = x[:, 2]
        ahead = z > 0
        cells = np.floor(x[:, :2] / np.where(ahead, z, 1.0)[:, None] / CELL_RAD).astype(np.int64)
        cells -= self.cell0
        h, w = self.zmin.shape
        inside = ahead & (cells[:, 0] >= 0) & (cells[:, 0] < w) & (cells[:, 1] >= 0) & (cells[:, 1] < h)
        rows, z, cells = rows[inside], z[inside], cells[inside]
        zmin = self.zmin[cells[:, 1], cells[:, 0]]
        counted = self.count[cells[:, 1], cells[:, 0]] > 0
        s, sj = np.asarray(sigma, float)[rows], self.sigma[cells[:, 1], cells[:, 0]]
        limit = K_SIGMA * np.sqrt(s * s + sj * sj)
        out[rows[counted & (zmin - z > limit)]] = True
        return out


def _neighbourhood(zmin: np.ndarray, full: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nearest depth over each cell's 3 x 3 neighbourhood, and whether all nine cells are
    full. Near a depth edge the decoder drops the pixels next to the jump: a cell there holds
    only the far surface, while the near one's edge passes through it; its neighbours hold
    the near surface's depth, and a cell beside an empty one does not speak."""
    h, w = zmin.shape
    z = np.pad(zmin, 1, constant_values=np.inf)
    f = np.pad(full, 1, constant_values=False)
    near, every = zmin.copy(), full.copy()
    for dy in range(3):
        for dx in range(3):
            near = np.minimum(near, z[dy:dy + h, dx:dx + w])
            every &= f[dy:dy + h, dx:dx + w]
    return near, every


@dataclass
class FreeSpace:
    """The depth views of a job's stations, and what the model loses to them."""

    views: list[DepthView] = field(default_factory=list)
    removed: dict[str, int] = field(default_factory=dict)
    tested: int = 0

    def add(self, view: DepthView) -> None:
        self.views = [v for v in self.views if v.name != view.name] + [view]

    def contradicted(self, points: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """Per world point: some station saw through it. Counts the removals by station."""
        pts = np.asarray(points, float)
        sig = np.nan_to_num(np.asarray(sigma, float), nan=0.0)
        out = np.zeros(len(pts), bool)
        if not len(pts):
            return out
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        for v in self.views:
            if np.any(v.lo - REACH_MM > hi) or np.any(v.hi + REACH_MM < lo):
                continue
            hit = v.saw_through(pts, sig) & ~out
            if hit.any():
                self.removed[v.name] = self.removed.get(v.name, 0) + int(hit.sum())
                out |= hit
        self.tested += len(pts)
        return out

    def keep(self, parts: Iterable[tuple[np.ndarray, np.ndarray]]
             ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """``parts`` (points, 1-sigma) without their contradicted points."""
        for p, s in parts:
            bad = self.contradicted(p, s)
            yield (p[~bad], s[~bad]) if bad.any() else (p, s)

    def to_json(self) -> dict[str, object]:
        n = sum(self.removed.values())
        return {"removed": n, "tested": self.tested,
                "share": n / self.tested if self.tested else 0.0,
                "by_station": dict(sorted(self.removed.items())), "k_sigma": K_SIGMA,
                "cell_mrad": round(CELL_RAD * 1e3, 3)}
