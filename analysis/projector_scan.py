"""A camera–projector scan: one camera's decoded projector coordinates into a cloud.

Pixels next to a depth edge or mixing two surfaces are masked first, with the per-pixel step
and bend limits of :mod:`scancell.analysis.decode_limits`; then every remaining pixel is
triangulated against the projector (:meth:`CameraProjectorRig.triangulate`). The cloud is in
the camera's optical frame (mm) and carries per-point quality (modulation, DN), intensity and a
1-sigma depth noise: the coordinate's noise times the depth change per projector px.
"""

from __future__ import annotations

import time

import numpy as np
from scancell.analysis import decode_limits as lim
from scancell.analysis.decode_limits import DecodeLimits
from scancell.analysis.pattern_decode import ViewDecode
from scancell.analysis.projector_rig import CameraProjectorRig
from scancell.analysis.stereo import Cloud, mask_discontinuities


def masked_coordinates(view: ViewDecode, limits: DecodeLimits) -> dict[str, np.ndarray]:
    """Each axis's coordinates with depth edges, mixed pixels and the border masked."""
    out = {}
    for axis, coord in view.coords.items():
        step, bend = lim.discontinuity_limits(coord, view.sigma[axis], limits)
        out[axis] = mask_discontinuities(coord, step, bend, limits.border_px)
    return out


def reconstruct(rig: CameraProjectorRig, view: ViewDecode, limits: DecodeLimits | None = None,
                timings: dict[str, float] | None = None) -> Cloud:
    """Triangulate one camera's decode against the projector; points in the camera frame."""
    limits = limits or DecodeLimits()
    t0 = time.perf_counter()
    h, w = view.modulation.shape
    rig.check_image_size(w, h, "the frames")
    masked = masked_coordinates(view, limits)
    ok = np.ones((h, w), bool)
    for c in masked.values():
        ok &= np.isfinite(c)
    rows, cols = np.nonzero(ok)
    t1 = time.perf_counter()
    u = masked["x"][rows, cols] if "x" in masked else None
    v = masked["y"][rows, cols] if "y" in masked else None
    X, per_px = rig.triangulate_with_sensitivity(rows, cols, u, v)
    good = np.isfinite(X).all(1) & (X[:, 2] > limits.z_min_mm) & (X[:, 2] < limits.z_max_mm)
    X, per_px, rows, cols = X[good], per_px[good], rows[good], cols[good]
    t2 = time.perf_counter()
    # the point's noise: the coordinate's (the column's, else the row's) times |∂X/∂coordinate|
    axis = "x" if "x" in view.sigma else "y"
    unc = (view.sigma[axis][rows, cols] * per_px).astype(np.float32)
    if timings is not None:
        timings.update(mask=t1 - t0, triangulate=t2 - t1, uncertainty=time.perf_counter() - t2)
    return Cloud(X.astype(np.float32), view.modulation[rows, cols].astype(np.float32),
                 view.background[rows, cols].astype(np.float32),
                 np.stack([cols, rows], 1).astype(np.int32), unc)
