"""Thin triangles cut until Embree's float32 closest points on them are exact enough.

A CAD tessellation by chordal tolerance alone leaves slivers on ruled faces: a straight fillet
along the car body comes out as 3900 x 2.2 mm triangles. Open3D's ``RaycastingScene`` (Embree)
finds closest points in float32, and on a triangle of longest edge e and altitude w the closest
point's position along the triangle carries an error of about

    δ ≈ ε · e³ / w²,    ε = 2⁻²⁴ (float32's half ulp)

(the barycentric weights are differences of products of edge dot products, of size e⁴, over
the squared area, of size e² w²). At e = 3900 mm and w = 2.2 mm that is 0.7 mm: measured
0.5-0.96 mm on the car body's fillets, where points that lie on the surface came out up to
1.08 mm off it, and 23 % of a station's points over 0.5 mm. Ray casting is unaffected (its
hits lie within 5e-5 mm of their triangle's plane).

:func:`slice_thin_triangles` cuts the triangles where δ exceeds a tolerance into pieces that
meet it, in their own plane: the surface stays the same. Subdividing all three edges
(trimesh's ``remesh.subdivide_to_size``, Open3D's ``subdivide_midpoint``) keeps a sliver's
shape and only shrinks δ by 2 a round; the cuts must run across the sliver.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: float32's half unit in the last place, relative
FLOAT32_EPS = 2.0 ** -24
#: the closest-point error the split aims at (mm): far below any scanner's noise
CLOSEST_POINT_TOLERANCE_MM = 1e-3
#: triangles thinner than this (altitude over longest edge) have no area to speak of: a
#: closest point on them is one on their edges, which its neighbours give; they are not split
DEGENERATE_ASPECT = 1e-6


def closest_point_error_mm(edge_mm: np.ndarray, altitude_mm: np.ndarray) -> np.ndarray:
    """The float32 closest point's error (mm) on triangles of longest edge ``edge_mm`` and
    altitude ``altitude_mm`` over it: ε e³ / w²."""
    return FLOAT32_EPS * edge_mm ** 3 / np.maximum(altitude_mm, 1e-12) ** 2


def thin_triangles(vertices: np.ndarray, triangles: np.ndarray,
                   tolerance_mm: float = CLOSEST_POINT_TOLERANCE_MM) -> np.ndarray:
    """Indices of the triangles whose float32 closest point may be off by more than
    ``tolerance_mm`` (degenerate ones left out: see :data:`DEGENERATE_ASPECT`)."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(triangles, np.int64).reshape(-1, 3)
    longest = np.linalg.norm(V[np.roll(F, -1, axis=1)] - V[F], axis=2).max(axis=1)
    twice_area = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                axis=1)
    altitude = twice_area / np.maximum(longest, 1e-300)
    return np.flatnonzero((closest_point_error_mm(longest, altitude) > tolerance_mm)
                          & (altitude > DEGENERATE_ASPECT * longest))


def _slice_fractions(length_mm: np.ndarray, width_mm: np.ndarray, tolerance_mm: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Per right triangle of leg ``length_mm`` from its apex and ``width_mm`` at its base: the
    fractions 0 < t_1 < ... < t_n = 1 of its length where it is cut across, as (owner, t). The
    apex triangle [0, t_1] is the whole scaled by t_1, its error δ0 t_1 (δ0 = ε ℓ³ / w²); a
    slice from t_j is at least t_j w wide, so its length may be (δ (t_j w)² / ε)^(1/3)."""
    delta0 = closest_point_error_mm(length_mm, width_mm)
    t = np.minimum(1.0, tolerance_mm / delta0)
    owners, cuts = [np.arange(len(t))], [t.copy()]
    live = np.flatnonzero(t < 1.0)
    while len(live):
        step = (tolerance_mm * (t[live] * width_mm[live]) ** 2 / FLOAT32_EPS) ** (1.0 / 3.0)
        t[live] = np.minimum(1.0, t[live] + step / length_mm[live])
        owners.append(live)
        cuts.append(t[live].copy())
        live = live[t[live] < 1.0]
    owner = np.concatenate(owners)
    order = np.lexsort((np.concatenate(cuts), owner))
    return owner[order], np.concatenate(cuts)[order]


def slice_thin_triangles(vertices: np.ndarray, triangles: np.ndarray,
                         tolerance_mm: float = CLOSEST_POINT_TOLERANCE_MM
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh with each of its :func:`thin_triangles` cut into pieces whose float32 closest
    point is within ``tolerance_mm``: first into two right triangles at the foot of its
    altitude onto its longest edge (an obtuse sliver is thin across every edge), then each
    right triangle across its length from its apex (:func:`_slice_fractions`): a triangle at
    the apex, trapezoids of two triangles after it. Returns vertices (the old ones first,
    unchanged), triangles (int32, the old winding) and each triangle's parent index.

    The pieces lie in their parent's plane and cover it: the surface is the same. Neighbours
    are not cut to match (a piece's corners lie on their edges): for closest points and
    distances that changes nothing; the mesh is for those, not for ray casting."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(triangles, np.int64).reshape(-1, 3)
    thin = thin_triangles(V, F, tolerance_mm)
    if not len(thin):
        return V, F.astype(np.int32), np.arange(len(F))
    G = F[thin]
    rows = np.arange(len(G))
    edge = np.linalg.norm(V[np.roll(G, -1, axis=1)] - V[G], axis=2)
    k = np.argmax(edge, axis=1)  # the longest edge a -> b; c opposite (the old winding)
    a, b, c = (V[G[rows, (k + j) % 3]] for j in range(3))
    ab = b - a
    foot = a + (np.einsum("ij,ij->i", c - a, ab) / np.einsum("ij,ij->i", ab, ab))[:, None] * ab
    # two right triangles (a, foot, c) and (b, c, foot), the right angle at the foot. Each is
    # cut from the apex at the end of its longer leg, as (apex X, Y, Z) in the old winding
    h = np.linalg.norm(c - foot, axis=1)
    legs = (np.linalg.norm(foot - a, axis=1), np.linalg.norm(b - foot, axis=1))
    corners = ((a, foot, c), (b, c, foot))
    X, Y, Z, length, width = [], [], [], [], []
    for (p, q, r), leg in zip(corners, legs, strict=True):
        along = (leg >= h)[:, None]  # apex p; otherwise apex c, which is r or q
        c_first = (c, p, q) if r is c else (c, r, p)
        X.append(np.where(along, p, c_first[0]))
        Y.append(np.where(along, q, c_first[1]))
        Z.append(np.where(along, r, c_first[2]))
        length.append(np.linalg.norm(c - p, axis=1))
        width.append(np.minimum(leg, h))
    X, Y, Z = (np.concatenate(u) for u in (X, Y, Z))
    parent_of = np.concatenate([thin, thin])
    # 10 % margin: a piece's longest edge is its diagonal, a little over the slice's length
    owner, t = _slice_fractions(np.concatenate(length), np.concatenate(width),
                                0.9 * tolerance_mm)
    P = X[owner] + t[:, None] * (Y - X)[owner]
    Q = X[owner] + t[:, None] * (Z - X)[owner]
    n0 = len(V)
    apex_id = n0 + np.arange(len(X))
    p_id = n0 + len(X) + np.arange(len(P))
    q_id = p_id + len(P)
    first = np.r_[True, owner[1:] != owner[:-1]]
    nxt = np.flatnonzero(~first)
    tris = [np.stack([apex_id[owner[first]], p_id[first], q_id[first]], axis=1),
            np.stack([p_id[nxt - 1], p_id[nxt], q_id[nxt]], axis=1),
            np.stack([p_id[nxt - 1], q_id[nxt], q_id[nxt - 1]], axis=1)]
    parents = [parent_of[owner[first]], parent_of[owner[nxt]], parent_of[owner[nxt]]]
    keep = np.ones(len(F), bool)
    keep[thin] = False
    out_f = np.concatenate([F[keep], *tris])
    out_p = np.concatenate([np.flatnonzero(keep), *parents])
    return np.concatenate([V, X, P, Q]), out_f.astype(np.int32), out_p


def closest_point_scene(vertices: np.ndarray, triangles: np.ndarray,
                        tolerance_mm: float = CLOSEST_POINT_TOLERANCE_MM
                        ) -> tuple[Any, np.ndarray | None]:
    """Open3D's ``RaycastingScene`` for closest points on the mesh, its thin triangles cut
    (:func:`slice_thin_triangles`), and the scene's triangle -> the mesh's triangle (int32;
    None where nothing was cut and the ids are the mesh's own)."""
    import open3d as o3d

    v, t, parent = slice_thin_triangles(vertices, triangles, tolerance_mm)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                        o3d.core.Tensor(t.astype(np.uint32)))
    cut = len(t) != len(np.asarray(triangles).reshape(-1, 3))
    return scene, parent.astype(np.int32) if cut else None
