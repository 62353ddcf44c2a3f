"""The emulated projectors' DMD as the simulated cell sees it.

An emulator displays 8-bit images. The simulated cell renders fringes analytically (a
``FringeSequence`` with its response and defocus), so :class:`WorldDisplay` recognises what
the images are: uniform levels, or the fringes of ``model/patterns.py``'s convention (vertical
fringes, ``periods`` across the image width, N steps), possibly through a pre-compensation
table, which it recovers. Any other image is refused with a clear error: the simulated
projector cannot render arbitrary pictures.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass

import numpy as np
from scancell.model.patterns import FringeSequence
from scancell.sim.cell import UNIFORM_BASE
from scancell.sim.world import SimWorld

log = logging.getLogger(__name__)


class UnrenderableImage(ValueError):
    pass


@dataclass(frozen=True)
class Fringes:
    sequence: FringeSequence
    precompensation: np.ndarray | None


def column_profile(image: np.ndarray) -> np.ndarray:
    """The row every row of a column pattern repeats; UnrenderableImage otherwise."""
    image = np.asarray(image)
    if image.ndim != 2 or not np.array_equal(image, np.broadcast_to(image[:1], image.shape)):
        raise UnrenderableImage("the simulated projector renders column patterns only (vertical "
                                "fringes or uniform levels); this image varies along columns")
    return image[0].astype(np.int64)


def _period(profile: np.ndarray) -> float:
    """Periods across the width of the profile's strongest frequency (parabolic peak)."""
    spectrum = np.abs(np.fft.rfft(profile - profile.mean()))
    k = int(np.argmax(spectrum[1:]) + 1)
    if 1 <= k < len(spectrum) - 1:
        a, b, c = spectrum[k - 1:k + 2]
        denom = a - 2 * b + c
        return k + (0.5 * (a - c) / denom if denom else 0.0)
    return float(k)


def _lut_for(seq: FringeSequence, profiles: list[np.ndarray], width: int) -> np.ndarray | None:
    """The table mapping each ideal 8-bit value to the one shown, if one table explains every
    profile; None if none does."""
    table = np.full(256, -1, np.int64)
    for k, shown in enumerate(profiles):
        ideal = seq.image(k, width, 1)[0].astype(np.int64)
        seen = table[ideal]
        if np.any((seen >= 0) & (seen != shown)):
            return None
        table[ideal] = shown
        if np.any(table[ideal] != shown):  # one ideal value shown as two values in this image
            return None
    known = np.flatnonzero(table >= 0)
    return np.round(np.interp(np.arange(256), known, table[known])).astype(np.int64)


def identify_fringes(profiles: list[np.ndarray]) -> Fringes:
    """The fringe sequence (and pre-compensation) whose 8-bit images are ``profiles``."""
    n, width = len(profiles), len(profiles[0])
    for steps in range(3, n + 1):
        if n % steps:
            continue
        estimates = [_period(profiles[j * steps]) for j in range(n // steps)]
        for rounding in (None, 2, 0):
            periods = tuple(float(p if rounding is None else round(p, rounding))
                            for p in estimates)
            try:
                seq = FringeSequence(periods, steps)
            except ValueError:
                continue
            lut = _lut_for(seq, profiles, width)
            if lut is not None:
                identity = np.array_equal(lut, np.arange(256))
                return Fringes(seq, None if identity else lut)
    raise UnrenderableImage(f"{n} images are neither uniform levels nor a fringe sequence of "
                            f"the scancell convention (model/patterns.py)")


def _digest(image: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()


class WorldDisplay:
    """Shows an emulator's patterns in a simulated world and pulses its trigger line."""

    def __init__(self, world: SimWorld) -> None:
        self.world = world
        self._known: dict[str, int] = {}   # image digest -> the cell's pattern index
        self._fringe_digests: set[str] = set()
        self._loaded: list[int] = []

    def load(self, images: list[np.ndarray]) -> None:
        """Make ``images`` displayable (UnrenderableImage if the cell cannot render them)."""
        digests = [_digest(im) for im in images]
        if not all(d in self._known for d in digests):
            profiles = [column_profile(im) for im in images]
            if all(np.all(p == p[0]) for p in profiles):
                for d, p in zip(digests, profiles, strict=True):
                    self._known[d] = UNIFORM_BASE - int(p[0])
            else:
                fringes = identify_fringes(profiles)
                with self.world.lock:
                    self.world.cell.load_sequence(fringes.sequence, fringes.precompensation)
                for d in self._fringe_digests:
                    self._known.pop(d, None)
                self._fringe_digests = set(digests)
                self._known.update({d: k for k, d in enumerate(digests)})
                log.info("simulated DMD: fringes %s x %d steps%s", fringes.sequence.periods,
                         fringes.sequence.steps,
                         " (pre-compensated)" if fringes.precompensation is not None else "")
        self._loaded = [self._known[d] for d in digests]

    def show(self, i: int) -> None:
        """Display loaded image ``i`` (-1: dark) and pulse trigger out. Never waits for the
        world's lock (a render may hold it for seconds): the pulse carries its pattern, and the
        shown pattern is one attribute."""
        index = -1 if i < 0 else self._loaded[i]
        self.world.cell.show(index)
        if i >= 0:
            self.world.trigger.pulse(index)
