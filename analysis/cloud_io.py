"""Point clouds to and from PLY.

Reading goes through Open3D's tensor API, which keeps the extra per-point fields. Writing is a
PLY header and one numpy record array: importing Open3D alone took 1.4 s of the 3.6 s a
``scancell decode`` process spent (measured, benchmarks/bench_cli_startup.py), for a format
that is a header and the bytes of a structured array. Files open in Open3D, CloudCompare and
any PLY reader (checked by test_scanner against Open3D's reader).

Writes go to a temporary file next to the target and are renamed on success, so a failed run
never leaves an empty or partial PLY behind.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np


class CloudFileError(ValueError):
    pass


def write_ply(path: str | Path, points: np.ndarray, fields: dict[str, np.ndarray] | None = None,
              ascii: bool = False, comments: list[str] | None = None) -> None:
    """Write (N, 3) ``points`` (mm) and optional per-point scalar ``fields`` (N,) as PLY;
    ``comments`` become header ``comment`` lines (one line each, e.g. ``key: value``)."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CloudFileError(f"{path}: points must be (N, 3), got {pts.shape}")
    write_ply_chunks(path, len(pts), list(fields or {}), [(pts, fields or {})], ascii, comments)


def write_ply_chunks(path: str | Path, count: int, field_names: list[str],
                     chunks: Iterable[tuple[np.ndarray, dict[str, np.ndarray]]],
                     ascii: bool = False, comments: list[str] | None = None) -> None:
    """Write a PLY of ``count`` points from ``chunks``, each ((M, 3) points mm, {name: (M,)
    values} for every one of ``field_names``), one chunk in memory at a time: a model larger
    than memory is written as it is read."""
    p = Path(path)
    if count == 0:
        raise CloudFileError(f"{p}: refusing to write an empty cloud")
    names = ["x", "y", "z"]
    for name in field_names:
        if not name.isidentifier() or name in names:
            raise CloudFileError(f"{p}: field name {name!r} is not a plain identifier")
        names.append(name)
    extra = [f"comment {c}\n" for c in comments or []]
    if any("\n" in c or "\r" in c or not c.isascii() for c in comments or []):
        raise CloudFileError(f"{p}: header comments must be single ASCII lines")
    header = "".join(["ply\n", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0\n",
                      "comment scancell: units mm\n", *extra, f"element vertex {count}\n",
                      *(f"property float {n}\n" for n in names), "end_header\n"])
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp.ply")
    written = 0
    try:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            for points, fields in chunks:
                rec = _ply_records(p, names, points, fields)
                if ascii:
                    np.savetxt(fh, rec.view(np.float32).reshape(len(rec), -1), fmt="%.7g")
                else:
                    rec.tofile(fh)
                written += len(rec)
        if written != count:
            raise CloudFileError(f"{p}: {written} points came for the {count} announced")
        os.replace(tmp, p)
    except OSError as exc:
        raise CloudFileError(f"{p}: cannot write: {exc.strerror or exc}") from None
    finally:
        tmp.unlink(missing_ok=True)


def _ply_records(p: Path, names: list[str], points: np.ndarray,
                 fields: dict[str, np.ndarray]) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CloudFileError(f"{p}: points must be (N, 3), got {pts.shape}")
    rec = np.empty(len(pts), dtype=[(n, "<f4") for n in names])
    for i, n in enumerate("xyz"):
        rec[n] = pts[:, i]
    for n in names[3:]:
        if n not in fields:
            raise CloudFileError(f"{p}: field {n!r} missing from a chunk")
        v = np.asarray(fields[n]).reshape(-1)
        if len(v) != len(pts):
            raise CloudFileError(f"{p}: field {n!r} has {len(v)} values for {len(pts)} points")
        rec[n] = v
    return rec


#: bytes of each PLY property type
_PLY_TYPE_SIZE = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2,
                  "int16": 2, "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4,
                  "float": 4, "float32": 4, "double": 8, "float64": 8}


def check_ply_length(p: Path) -> None:
    """CloudFileError if a binary PLY holds fewer bytes than its header announces (a file cut
    short in a copy or a full disk: a reader would fill the rest with garbage). Only files
    whose elements all have fixed-size properties (no lists) are checked; ASCII files are
    left to the reader."""
    with open(p, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return
    lines = head[:end].decode("ascii", "replace").splitlines()
    if not any(line.startswith("format binary") for line in lines):
        return
    body = end + len(b"end_header") + (2 if head[end + 10:end + 12] == b"\r\n" else 1)
    need, count, row = 0, 0, 0
    for line in lines:
        words = line.split()
        if not words:
            continue
        if words[0] == "element":
            need += count * row
            count, row = int(words[2]), 0
        elif words[0] == "property":
            if words[1] == "list" or words[1] not in _PLY_TYPE_SIZE:
                return
            row += _PLY_TYPE_SIZE[words[1]]
    need += count * row
    have = p.stat().st_size - body
    if have < need:
        raise CloudFileError(f"{p}: truncated: its header announces {need} bytes of data, the file "
                             f"holds {have} ({have / need:.1%}); copy it again")


def read_ply(path: str | Path, dtype: type = np.float64) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(points (N, 3) of ``dtype``, extra scalar fields) of a PLY file (float32: as a scanner's
    PLY stores them, half the memory of a large cloud)."""
    import open3d as o3d

    p = Path(path)
    if not p.is_file():
        raise CloudFileError(f"{p}: no such file")
    check_ply_length(p)
    cloud = o3d.t.io.read_point_cloud(str(p))
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        raise CloudFileError(f"{p}: no points (not a point cloud PLY, or empty)")
    pts = cloud.point.positions.numpy().astype(dtype)
    fields = {k: cloud.point[k].numpy().reshape(-1) for k in cloud.point
              if k != "positions" and cloud.point[k].numpy().ndim <= 2
              and cloud.point[k].numpy().reshape(len(pts), -1).shape[1] == 1}
    return pts, fields
