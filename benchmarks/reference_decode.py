"""Plain-numpy reference of the scanner's decode, for bench_decode_speed.py.

The same steps and the same maths as scancell.analysis (phase, heterodyne unwrapping with the
consistency check, rectification by bilinear interpolation, phase matching along rows,
triangulation), written the straightforward way: float64 numpy, np.mod/np.arctan2, numpy
bilinear interpolation instead of cv2.remap, one np.searchsorted per row.
"""

from __future__ import annotations

import numpy as np


def wrapped_phase(images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = len(images)
    stack = np.stack([im.astype(np.float64) for im in images])
    d = 2 * np.pi * np.arange(n) / n
    s = np.tensordot(np.sin(d), stack, 1)
    c = np.tensordot(np.cos(d), stack, 1)
    return np.mod(np.arctan2(s, c), 2 * np.pi), 2 / n * np.hypot(s, c), stack.mean(0)


def decode(images: list[np.ndarray], periods=(70.0, 64.0, 59.0), steps: int = 3,
           width: int = 1280, min_mod: float = 8.0, tol: float = 1.0, margin_max: float = 0.3
           ) -> np.ndarray:
    phases, mods = [], []
    sat = np.zeros(images[0].shape, bool)
    for j in range(len(periods)):
        phi, b, _ = wrapped_phase(images[j * steps:(j + 1) * steps])
        phases.append(phi)
        mods.append(b)
        for im in images[j * steps:(j + 1) * steps]:
            sat |= im >= 254.5
    two_pi = 2 * np.pi
    p1, p2, p3 = periods
    b12 = np.mod(phases[0] - phases[1], two_pi)
    b23 = np.mod(phases[1] - phases[2], two_pi)
    top = np.mod(b12 - b23, two_pi)
    margin = np.zeros_like(top)

    def unwrap(phi, ref, ratio):
        o = (ref * ratio - phi) / two_pi
        k = np.round(o)
        np.maximum(margin, np.abs(o - k), out=margin)
        return phi + two_pi * k

    a12 = unwrap(b12, top, p1 - p2)
    a23 = unwrap(b23, top, p2 - p3)
    a1 = unwrap(phases[0], a12, p1 / (p1 - p2))
    a2 = unwrap(phases[1], a23, p2 / (p2 - p3))
    a3 = unwrap(phases[2], a23, p3 / (p2 - p3))
    est = [a * width / (two_pi * p) for a, p in zip((a1, a2, a3), periods, strict=True)]
    w = np.array(periods) ** 2
    col = (w[0] * est[0] + w[1] * est[1] + w[2] * est[2]) / w.sum()
    spread = np.zeros_like(col)
    for e, p in zip(est, periods, strict=True):
        t = max(tol, 0.1 * width / p)
        spread = np.maximum(spread, np.abs(e - col) * tol / t)
    bad = (np.minimum.reduce(mods) < min_mod) | sat | (spread > tol) | (margin > margin_max)
    col[bad] = np.nan
    return col


def remap(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    h, w = img.shape
    x0, y0 = np.floor(mx).astype(np.int64), np.floor(my).astype(np.int64)
    fx, fy = mx - x0, my - y0
    inside = (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1)
    x0c, y0c = np.clip(x0, 0, w - 2), np.clip(y0, 0, h - 2)
    v = (img[y0c, x0c] * (1 - fx) * (1 - fy) + img[y0c, x0c + 1] * fx * (1 - fy)
         + img[y0c + 1, x0c] * (1 - fx) * fy + img[y0c + 1, x0c + 1] * fx * fy)
    v[~inside] = np.nan
    return v


def match(col_l: np.ndarray, col_r: np.ndarray, max_step: float):
    rows, xls, xrs = [], [], []
    for r in range(col_l.shape[0]):
        right = col_r[r]
        ok = np.isfinite(right)
        xs = np.flatnonzero(ok)
        vals = right[ok]
        if len(vals) < 2:
            continue
        mono = np.concatenate([[True], vals[1:] > np.maximum.accumulate(vals)[:-1]])
        xs, vals = xs[mono], vals[mono]
        if len(vals) < 2:
            continue
        left = col_l[r]
        xl = np.flatnonzero(np.isfinite(left))
        q = left[xl]
        i1 = np.searchsorted(vals, q)
        good = (i1 > 0) & (i1 < len(vals))
        i1 = np.where(good, i1, 1)
        i0 = i1 - 1
        step = vals[i1] - vals[i0]
        good &= (xs[i1] - xs[i0] == 1) & (step <= max_step)
        t = (q - vals[i0]) / np.where(step > 0, step, 1)
        rows.append(np.full(good.sum(), r))
        xls.append(xl[good])
        xrs.append((xs[i0] + t)[good])
    return np.concatenate(rows), np.concatenate(xls), np.concatenate(xrs)


def triangulate(rows, xl, xr, rect) -> np.ndarray:
    d = (xl - rect.cx1) - (xr - rect.cx2)
    z = rect.f * rect.baseline_mm / d
    p = np.stack([(xl - rect.cx1) * z / rect.f, (rows - rect.cy) * z / rect.f, z], 1)
    good = d > 0
    return (p[good] @ rect.R1)


def read_calibration(path: str) -> dict[str, np.ndarray]:
    """The stereo.yaml keys (OpenCV FileStorage) the decode needs."""
    import cv2

    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    out = {k: fs.getNode(k).mat() for k in ("K1", "D1", "K2", "D2", "R", "T")}
    out["size"] = np.array([int(fs.getNode("image_width").real()),
                            int(fs.getNode("image_height").real())])
    fs.release()
    return out


def main(argv: list[str] | None = None) -> int:
    """``python reference_decode.py --calib stereo.yaml --images DIR --out cloud.ply``: the
    whole decode as a process, the plain way (numpy and OpenCV only, no scancell), for
    bench_cli_startup.py to set ``scancell decode`` against."""
    import argparse
    import time

    import cv2

    p = argparse.ArgumentParser()
    p.add_argument("--calib", required=True)
    p.add_argument("--images", required=True)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    c = read_calibration(a.calib)
    images = {}
    for role in ("left", "right"):
        files = sorted(f for f in __import__("pathlib").Path(a.images, role).iterdir()
                        if f.suffix == ".png")
        images[role] = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    size = (int(c["size"][0]), int(c["size"][1]))
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(c["K1"], c["D1"], c["K2"], c["D2"], size, c["R"],
                                                c["T"].reshape(3, 1), flags=0, alpha=-1)
    maps1 = cv2.initUndistortRectifyMap(c["K1"], c["D1"], R1, P1, size, cv2.CV_32FC1)
    maps2 = cv2.initUndistortRectifyMap(c["K2"], c["D2"], R2, P2, size, cv2.CV_32FC1)
    rl = remap(decode(images["left"]), *maps1)
    rr = remap(decode(images["right"]), *maps2)
    rows, xl, xr = match(rl, rr, max_step=3.0)
    f, cx1, cy, cx2 = P1[0, 0], P1[0, 2], P1[1, 2], P2[0, 2]
    baseline = float(np.linalg.norm(c["T"]))
    d = (xl - cx1) - (xr - cx2)
    good = d > 0
    z = f * baseline / d[good]
    pts = np.stack([(xl[good] - cx1) * z / f, (rows[good] - cy) * z / f, z], 1) @ R1
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    with open(a.out, "wb") as fh:
        fh.write(header.encode())
        fh.write(pts.astype("<f4").tobytes())
    print(f"{len(pts)} points -> {a.out} in {time.perf_counter() - t0:.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
