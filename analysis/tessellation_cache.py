"""A STEP file's tessellation kept on disk, keyed by its geometry and the tolerances.

OpenCASCADE meshes the car rear's B-rep at a 0.01 mm chordal tolerance in about 21 s (the
surface-deflection control is most of it); a quality engineer inspects scan after scan against
the same CAD. The key is the SHA-256 of the file's ``DATA`` section (the header holds the file
name and the time it was written, which change with every export of the same geometry), the
chordal and angular tolerances and :data:`VERSION`.

The cache lives in ``$SCANCELL_CACHE_DIR`` or ``$XDG_CACHE_HOME/scancell`` (``~/.cache/scancell``);
``SCANCELL_CACHE_DIR=off`` turns it off. An entry is written to a temporary file and renamed, so
two processes tessellating the same file at once leave one whole entry. An entry that cannot be
read is tessellated again and replaced; a cache that cannot be written is only logged.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

#: bump when the tessellation's arithmetic changes: old entries are then never read
VERSION = 1


def cache_dir() -> Path | None:
    """Where entries go, or None when ``SCANCELL_CACHE_DIR=off``."""
    explicit = os.environ.get("SCANCELL_CACHE_DIR")
    if explicit == "off":
        return None
    if explicit:
        return Path(explicit) / "nominal"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "scancell" / "nominal"


def entry_key(step_bytes: bytes, chordal_mm: float, angular_rad: float) -> str:
    start = step_bytes.find(b"\nDATA;")
    body = step_bytes[start:] if start >= 0 else step_bytes
    h = hashlib.sha256(body)
    h.update(f"\0{chordal_mm!r}\0{angular_rad!r}\0{VERSION}".encode())
    return h.hexdigest()[:40]


def read(key: str) -> dict[str, np.ndarray] | None:
    """The arrays stored under ``key`` (vertices, triangles, face_of_triangle, face_names, unit),
    or None."""
    root = cache_dir()
    if root is None:
        return None
    path = root / f"{key}.npz"
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return {name: z[name] for name in
                    ("vertices", "triangles", "face_of_triangle", "face_names", "unit")}
    except (OSError, ValueError, KeyError) as exc:
        log.warning("tessellation cache %s unreadable (%s): tessellating again", path, exc)
        return None


def write(key: str, **arrays: np.ndarray) -> None:
    root = cache_dir()
    if root is None:
        return
    tmp = None
    try:
        root.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=root, suffix=".tmp")
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, root / f"{key}.npz")
        tmp = None
    except OSError as exc:
        log.warning("tessellation cache %s not written: %s", root, exc)
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
