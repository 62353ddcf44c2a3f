"""Pattern set specs and frame folders on disk.

- :func:`load_pattern_set`: a preset name (``model.pattern_set.PRESETS``) or a
  ``.toml``/``.json`` spec file (:mod:`scancell.model.pattern_set`);
- :func:`find_frames`: a view's frames in a folder: the spec's ``frames`` glob or list, or
  else every image file (BMP, PNG, TIFF, PGM) in natural name order (``f2`` before ``f10``);
- :func:`read_frames`: the frames as they are (8, 12 or 16 bit, one channel).
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scancell.analysis.scanner import ImageSetError, read_image
from scancell.model.pattern_set import (
    PRESETS,
    PatternSet,
    PatternSpecError,
    preset,
    presets_of_length,
)

FRAME_SUFFIXES = (".bmp", ".png", ".tif", ".tiff", ".pgm")


def load_pattern_set(spec: str | Path) -> PatternSet:
    """A preset by name, or a spec file (TOML or JSON); PatternSpecError names the file."""
    name = str(spec)
    if name in PRESETS:
        return preset(name)
    p = Path(name)
    if not p.is_file():
        raise PatternSpecError(f"{name}: neither a preset ({', '.join(PRESETS)}) nor a spec file")
    text = p.read_text(encoding="utf-8")
    try:
        data = json.loads(text) if p.suffix.lower() == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise PatternSpecError(f"{p}: not valid {'JSON' if p.suffix.lower() == '.json' else 'TOML'}: "
                               f"{exc}") from None
    return PatternSet.from_dict(data, str(p))


def _natural_key(path: Path) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def find_frames(folder: str | Path, spec: PatternSet) -> list[Path]:
    """The view's frame files in sequence order; ImageSetError naming the folder."""
    root = Path(folder)
    if not root.is_dir():
        raise ImageSetError(f"{root}: no such directory")
    if isinstance(spec.frames, str):
        paths = sorted((p for p in root.glob(spec.frames) if p.is_file()), key=_natural_key)
        how = f"matching {spec.frames!r}"
    elif spec.frames is not None:
        paths = [root / f for f in spec.frames]
        missing = [p for p in paths if not p.is_file()]
        if missing:
            raise ImageSetError(f"{missing[0]}: listed in the pattern set's frames but missing")
        how = "listed"
    else:
        paths = sorted((p for p in root.iterdir()
                        if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES), key=_natural_key)
        how = f"({', '.join(FRAME_SUFFIXES)})"
    if not paths:
        raise ImageSetError(f"{root}: no frames {how}")
    if len(paths) != len(spec):
        fits = presets_of_length(len(paths))
        hint = f"; presets of {len(paths)} frames: {', '.join(fits)}" if fits else ""
        raise ImageSetError(
            f"{root}: {len(paths)} frames {how}, but the pattern set {spec.name or ''} needs "
            f"{len(spec)} (set 'frames' in the spec to pick them{hint})".replace("  ", " "))
    return paths


def read_frames(paths: Sequence[Path]) -> tuple[list[np.ndarray], list[str]]:
    """The frames, one channel each, at their own bit depth; ImageSetError naming a file."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:  # image decoding releases the GIL
        frames = list(pool.map(read_image, paths))
    return frames, [str(p) for p in paths]
