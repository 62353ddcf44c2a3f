"""Per-pixel kernels (numba) of the simulated cameras' renderer.

The same arithmetic as numpy on 5 M pixels, in one parallel pass instead of a dozen float64
temporaries: at 2448 x 2048 the numpy version spent 5.2 s per camera and pose outside the ray
cast itself, mostly moving rays between frames, projecting into the projector and shading
(benchmarks/bench_render.py). tests/test_sim.py checks the kernels against the numpy models.
"""

from __future__ import annotations

import math

import numba
import numpy as np

numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]


def move_rays(rays: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rays (N, 6) float32, origin then unit direction, moved by ``x -> R x + t``."""
    if len(rays) < 4096:  # e.g. the tracker's beam checks: waking the kernel's threads costs more
        return np.hstack([rays[:, :3] @ R.T + t, rays[:, 3:] @ R.T]).astype(np.float32)
    return _move_rays(rays, R, t)


@numba.njit(parallel=True, cache=True)
def _move_rays(rays: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    n = rays.shape[0]
    out = np.empty((n, 6), np.float32)
    for i in numba.prange(n):
        for r in range(3):
            out[i, r] = (R[r, 0] * rays[i, 0] + R[r, 1] * rays[i, 1] + R[r, 2] * rays[i, 2]
                         + t[r])
            out[i, 3 + r] = R[r, 0] * rays[i, 3] + R[r, 1] * rays[i, 4] + R[r, 2] * rays[i, 5]
    return out


def rays_near_sphere(rays: np.ndarray, tfar: np.ndarray, centre: np.ndarray,
                     radius: float) -> np.ndarray:
    """True for each ray (N, 6) float32 whose segment from its origin to ``tfar`` (per ray)
    passes within ``radius`` of ``centre``: the only rays that can hit an object inside that
    sphere."""
    if len(rays) < 4096:  # the tracker's beam checks, from its server's thread: see move_rays
        v = np.asarray(centre, np.float64) - rays[:, :3]
        t = np.clip(np.einsum("ij,ij->i", v, rays[:, 3:]), 0.0, tfar)
        return np.einsum("ij,ij->i", d := v - t[:, None] * rays[:, 3:], d) <= radius * radius
    return _rays_near_sphere(rays, tfar, np.asarray(centre, np.float64), float(radius))


@numba.njit(parallel=True, cache=True)
def _rays_near_sphere(rays: np.ndarray, tfar: np.ndarray, centre: np.ndarray,
                      radius: float) -> np.ndarray:
    n = rays.shape[0]
    out = np.zeros(n, np.bool_)
    r2 = radius * radius
    for i in numba.prange(n):
        vx = centre[0] - rays[i, 0]
        vy = centre[1] - rays[i, 1]
        vz = centre[2] - rays[i, 2]
        t = vx * rays[i, 3] + vy * rays[i, 4] + vz * rays[i, 5]
        t = min(max(t, 0.0), tfar[i])
        dx = vx - t * rays[i, 3]
        dy = vy - t * rays[i, 4]
        dz = vz - t * rays[i, 5]
        out[i] = dx * dx + dy * dy + dz * dz <= r2
    return out


@numba.njit(parallel=True, cache=True)
def keep_nearer(best_t: np.ndarray, normal: np.ndarray, index: np.ndarray,
                primitive: np.ndarray, dirs: np.ndarray, sel: np.ndarray,
                t: np.ndarray, normal_obj: np.ndarray, R: np.ndarray, obj: int,
                primitive_obj: np.ndarray) -> None:
    """Merge one object's hits into the nearest hits so far, in place. Ray ``sel[j]`` met the
    object at ``t[j]`` on triangle ``primitive_obj[j]`` with normal ``normal_obj[j]`` (object
    frame); where that is nearer than ``best_t``, the ray takes the
    distance, the normal turned to world by ``R`` and facing the ray's origin (``dirs``: the
    rays' world directions), the object's index and the triangle."""
    for j in numba.prange(t.shape[0]):
        i = sel[j]
        if not t[j] < best_t[i]:
            continue
        best_t[i] = t[j]
        n0 = R[0, 0] * normal_obj[j, 0] + R[0, 1] * normal_obj[j, 1] + R[0, 2] * normal_obj[j, 2]
        n1 = R[1, 0] * normal_obj[j, 0] + R[1, 1] * normal_obj[j, 1] + R[1, 2] * normal_obj[j, 2]
        n2 = R[2, 0] * normal_obj[j, 0] + R[2, 1] * normal_obj[j, 1] + R[2, 2] * normal_obj[j, 2]
        if n0 * dirs[i, 0] + n1 * dirs[i, 1] + n2 * dirs[i, 2] > 0:
            n0, n1, n2 = -n0, -n1, -n2
        normal[i, 0] = n0
        normal[i, 1] = n1
        normal[i, 2] = n2
        index[i] = obj
        primitive[i] = primitive_obj[j]


@numba.njit(parallel=True, cache=True)
def rays_from_point(dirs: np.ndarray, R: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Rays (N, 6) float32 from one ``origin`` along ``R @ dirs[i]`` (dirs (N, 3) float32)."""
    n = dirs.shape[0]
    out = np.empty((n, 6), np.float32)
    for i in numba.prange(n):
        for r in range(3):
            out[i, r] = origin[r]
            out[i, 3 + r] = R[r, 0] * dirs[i, 0] + R[r, 1] * dirs[i, 1] + R[r, 2] * dirs[i, 2]
    return out


@numba.njit(parallel=True, cache=True)
def projector_terms(dirs_cam: np.ndarray, t_hit: np.ndarray, normal_world: np.ndarray,
                    R_wc: np.ndarray, R_pc: np.ndarray, t_pc: np.ndarray,
                    K: np.ndarray, dist: np.ndarray, width: int, height: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For every camera pixel with a hit (``t_hit`` finite): the projector column and row
    (NaN where the point is behind the projector, outside its image or turned away from it),
    the cosine of the projector's incidence, the distance to the projector (mm), and the cosine
    between the normal and the half vector of the projector and camera directions (for a
    specular lobe). Shadows are :func:`shadowed`'s.

    ``R_wc``: camera to world (rotation); ``R_pc, t_pc``: camera to projector; ``K, dist``: the
    projector's intrinsics and Brown–Conrady (k1, k2, p1, p2, k3) coefficients.
    """
    n = dirs_cam.shape[0]
    proj_x = np.full(n, np.nan)
    proj_y = np.full(n, np.nan)
    cos_p = np.zeros(n, np.float32)
    d_p = np.zeros(n, np.float32)
    cos_h = np.zeros(n, np.float32)
    # the projector's centre in the camera frame: -R_pc^T t_pc
    pc = np.empty(3)
    for r in range(3):
        pc[r] = -(R_pc[0, r] * t_pc[0] + R_pc[1, r] * t_pc[1] + R_pc[2, r] * t_pc[2])
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for i in numba.prange(n):
        t = t_hit[i]
        if not math.isfinite(t):
            continue
        x0 = dirs_cam[i, 0] * t
        x1 = dirs_cam[i, 1] * t
        x2 = dirs_cam[i, 2] * t
        v0, v1, v2 = pc[0] - x0, pc[1] - x1, pc[2] - x2
        dd = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        v0, v1, v2 = v0 / dd, v1 / dd, v2 / dd
        # the same direction in world
        w0 = R_wc[0, 0] * v0 + R_wc[0, 1] * v1 + R_wc[0, 2] * v2
        w1 = R_wc[1, 0] * v0 + R_wc[1, 1] * v1 + R_wc[1, 2] * v2
        w2 = R_wc[2, 0] * v0 + R_wc[2, 1] * v1 + R_wc[2, 2] * v2
        c = normal_world[i, 0] * w0 + normal_world[i, 1] * w1 + normal_world[i, 2] * w2
        cos_p[i] = c
        # half vector of the projector direction and the direction back to the camera
        h0 = v0 - dirs_cam[i, 0]
        h1 = v1 - dirs_cam[i, 1]
        h2 = v2 - dirs_cam[i, 2]
        hn = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2) + 1e-30
        hw0 = (R_wc[0, 0] * h0 + R_wc[0, 1] * h1 + R_wc[0, 2] * h2) / hn
        hw1 = (R_wc[1, 0] * h0 + R_wc[1, 1] * h1 + R_wc[1, 2] * h2) / hn
        hw2 = (R_wc[2, 0] * h0 + R_wc[2, 1] * h1 + R_wc[2, 2] * h2) / hn
        cos_h[i] = max(0.0, normal_world[i, 0] * hw0 + normal_world[i, 1] * hw1
                       + normal_world[i, 2] * hw2)
        d_p[i] = dd
        xp = R_pc[0, 0] * x0 + R_pc[0, 1] * x1 + R_pc[0, 2] * x2 + t_pc[0]
        yp = R_pc[1, 0] * x0 + R_pc[1, 1] * x1 + R_pc[1, 2] * x2 + t_pc[1]
        zp = R_pc[2, 0] * x0 + R_pc[2, 1] * x1 + R_pc[2, 2] * x2 + t_pc[2]
        if zp <= 1.0 or c <= 0.0:
            continue
        a = xp / zp
        b = yp / zp
        r2 = a * a + b * b
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        ad = a * radial + 2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a)
        bd = b * radial + p1 * (r2 + 2.0 * b * b) + 2.0 * p2 * a * b
        u = K[0, 0] * ad + K[0, 1] * bd + K[0, 2]
        v = K[1, 1] * bd + K[1, 2]
        if u < -0.5 or u > width - 0.5 or v < -0.5 or v > height - 0.5:
            continue
        proj_x[i] = u
        proj_y[i] = v
    return proj_x, proj_y, cos_p, d_p, cos_h


@numba.njit(parallel=True, cache=True)
def surface_terms(proj_x: np.ndarray, cos_p: np.ndarray, dist_p: np.ndarray, t_hit: np.ndarray,
                  kd: np.ndarray, lobe: np.ndarray, gain: float, ambient: float, d0: float,
                  k_p: float, focus_p: float, k_c: float, focus_c: float, psf_px: float,
                  scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per camera pixel (float32): the DN per unit projector light (``gain · cos_p · (d0 /
    d)² · (kd + lobe)``, 0 where the projector does not light it, ``proj_x`` NaN), the ambient
    DN (``gain · kd · ambient``), the projector's defocus blur at the surface (``k_p · |d −
    focus_p| / d``, projector px) and the camera's blur (its defocus ``k_c · |t − focus_c| /
    t`` at the hit, focus_c where nothing is hit, and the in-focus PSF ``psf_px``, in
    quadrature, over ``scale``). d: the distance to the projector, t: to the camera, both
    clipped at 1 mm; k: :func:`scancell.sim.optics_profile.defocus_px_per_unit`."""
    n = proj_x.shape[0]
    fringe = np.empty(n, np.float32)
    base = np.empty(n, np.float32)
    sigma_p = np.empty(n, np.float32)
    sigma_c = np.empty(n, np.float32)
    for i in numba.prange(n):
        d = max(dist_p[i], 1.0)
        if math.isfinite(proj_x[i]):
            c = min(max(cos_p[i], 0.0), 1.0)
            fringe[i] = gain * c * (d0 / d) * (d0 / d) * (kd[i] + lobe[i])
        else:
            fringe[i] = 0.0
        base[i] = gain * kd[i] * ambient
        sigma_p[i] = k_p * abs(d - focus_p) / d
        t = max(t_hit[i], 1.0) if math.isfinite(t_hit[i]) else focus_c
        dof = k_c * abs(t - focus_c) / t
        sigma_c[i] = math.sqrt(dof * dof + psf_px * psf_px) / scale
    return fringe, base, sigma_p, sigma_c


@numba.njit(parallel=True, cache=True)
def shadowed(proj_x: np.ndarray, proj_y: np.ndarray, dist_mm: np.ndarray, depth: np.ndarray,
             step: int, tol_mm: float) -> np.ndarray:
    """True where a point the projector would light at pixel (``proj_x``, ``proj_y``), at
    ``dist_mm`` from its centre, lies behind the first surface the projector lights there.

    ``depth`` (H', W'): the distance (mm, inf where nothing) to the first surface along the
    ray of every ``step``-th projector pixel (a shadow map), from pixel ``-step`` on. A point
    counts as lit when it is no farther than the farthest of the four samples around it plus
    ``tol_mm``. So a surface does not shadow itself (a plane's depth along the projector's rays
    is the reciprocal of an affine function of the image coordinates, convex: inside a cell of
    samples it stays below the corners' largest; a curved panel's sagitta over a 0.3 mm cell is
    well under a µm), and a shadow's edge moves by less than one sample towards its occluder."""
    n = proj_x.shape[0]
    h, w = depth.shape
    out = np.zeros(n, np.bool_)
    for i in numba.prange(n):
        u = proj_x[i]
        if not math.isfinite(u):
            continue
        a = u / step + 1.0  # the map's first sample lies one step before pixel 0
        b = proj_y[i] / step + 1.0
        c0 = min(max(math.floor(a), 0), w - 1)
        r0 = min(max(math.floor(b), 0), h - 1)
        c1 = min(c0 + 1, w - 1)
        r1 = min(r0 + 1, h - 1)
        far = max(max(depth[r0, c0], depth[r0, c1]), max(depth[r1, c0], depth[r1, c1]))
        out[i] = dist_mm[i] > far + tol_mm
    return out


# no "nnan": NaN marks pixels the projector does not light
@numba.njit(parallel=True, cache=True, fastmath={"contract", "arcp", "reassoc", "afn"})
def pattern_dn(base: np.ndarray, fringe: np.ndarray, proj_x: np.ndarray, sigma_p: np.ndarray,
               fringe_mode: bool, cycles_per_px: float, shift: float, coeffs: np.ndarray,
               uniform_light: float, brightness: float) -> np.ndarray:
    """Irradiance in DN (H, W float32) under one projector pattern.

    ``fringe_mode``: light ``Σ_k c_k · exp(−2π² σ² k² ν²) · cos(k θ)`` with θ = 2π ν x − shift
    at projector column x, ν = ``cycles_per_px`` and ``coeffs`` c_k the response's harmonics
    (:func:`scancell.sim.optics_profile.response_harmonics`); σ = ``sigma_p`` the projector's
    defocus blur at the pixel (projector px), which damps harmonic k by the Gaussian's transfer
    function. Otherwise the uniform ``uniform_light``. Unlit pixels (x NaN) get ambient only.
    """
    h, w = base.shape
    out = np.empty((h, w), np.float32)
    two_pi = 2.0 * math.pi
    nk = coeffs.shape[0]
    damp0 = -2.0 * math.pi * math.pi * cycles_per_px * cycles_per_px
    for r in numba.prange(h):
        for c in range(w):
            x = proj_x[r, c]
            if not math.isfinite(x):
                light = 0.0
            elif not fringe_mode:
                light = uniform_light
            else:
                theta = two_pi * cycles_per_px * x - shift
                ct = math.cos(theta)
                # damping of harmonic k: q^(k²), built up as q^(k²) = q^((k-1)²) · q^(2k-1)
                q = math.exp(sigma_p[r, c] * sigma_p[r, c] * damp0)
                q2 = q * q
                step = q
                damp = 1.0
                light = coeffs[0]
                prev, cur = 1.0, ct  # Chebyshev: cos(kθ) = 2 cosθ cos((k−1)θ) − cos((k−2)θ)
                for k in range(1, nk):
                    damp *= step
                    step *= q2
                    light += coeffs[k] * damp * cur
                    prev, cur = cur, 2.0 * ct * cur - prev
            out[r, c] = (base[r, c] + fringe[r, c] * light) * brightness
    return out


@numba.njit(parallel=True, cache=True)
def quantise(dn: np.ndarray, noise: np.ndarray, noise_dn: float, exposure: float = 1.0
             ) -> np.ndarray:
    """8-bit image: ``exposure * dn + noise_dn * noise`` rounded half to even and clipped to
    0..255."""
    h, w = dn.shape
    out = np.empty((h, w), np.uint8)
    for r in numba.prange(h):
        for c in range(w):
            v = np.rint(exposure * dn[r, c] + noise_dn * noise[r, c])
            out[r, c] = 0 if v < 0 else (255 if v > 255 else np.uint8(v))
    return out


@numba.njit(parallel=True, cache=True)
def sensor_dn(dn: np.ndarray, noise: np.ndarray, k_dn_per_e: float, dark_noise_e: float,
              dark_e: float, exposure: float = 1.0) -> np.ndarray:
    """8-bit image after the EMVA 1288 linear camera model: signal ``exposure · dn / K``
    electrons (``dn``: the irradiance at the nominal exposure and unit gain) plus
    ``dark_e`` dark-current electrons, temporal noise of variance ``σ_d² + μ_e`` electrons²
    (read noise and shot noise, the Poisson law by its normal approximation), times the system
    gain K (DN/e⁻), rounded (quantisation noise 1/12 DN²) and clipped at 0 and 255
    (saturation)."""
    h, w = dn.shape
    out = np.empty((h, w), np.uint8)
    for r in numba.prange(h):
        for c in range(w):
            e = max(exposure * dn[r, c] / k_dn_per_e, 0.0) + dark_e
            sigma = math.sqrt(dark_noise_e * dark_noise_e + e)
            v = np.rint(k_dn_per_e * (e + sigma * noise[r, c]))
            out[r, c] = 0 if v < 0 else (255 if v > 255 else np.uint8(v))
    return out


@numba.njit(parallel=True, cache=True)
def blend_levels(stack: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Per pixel, linear interpolation between images ``stack[i]`` and ``stack[i + 1]`` at the
    fractional index ``pos`` (H, W): a spatially varying blur from a few uniform ones."""
    h, w = pos.shape
    out = np.empty((h, w), np.float32)
    for r in numba.prange(h):
        for c in range(w):
            p = pos[r, c]
            i = int(p)
            f = p - i
            out[r, c] = stack[i, r, c] * (1.0 - f) + stack[i + 1, r, c] * f
    return out
