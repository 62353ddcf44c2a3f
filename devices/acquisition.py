"""Coupled projector/camera acquisition of a pattern sequence.

The projector's trigger output exposes every camera once per pattern. A projector is either
stepped (``show(k)`` for each pattern) or plays the loaded sequence itself (``play()``: a TI
LightCrafter running its pattern LUT). Frame k of every camera must belong to pattern k, and
this module proves it for each frame rather than assuming it:

- every camera delivers exactly one frame per pattern before the next pattern is shown (a lost
  pulse is a missing frame; a doubled pulse is an extra frame waiting in the queue);
- the camera's trigger counter, where it has one, advances by exactly one per pattern;
- the frame arrived after its pattern was shown (no frame left over from before).

Any violation raises :class:`CouplingError` naming the camera and the pattern.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from scancell.devices.base import Camera, Frame, Projector
from scancell.devices.errors import DeviceError, Timeout
from scancell.protocols.messages import now_ns

#: Each pattern stays up this much longer than the cameras expose (trigger latency, µs).
DISPLAY_MARGIN_US = 500


def display_us(cameras: Sequence[Camera]) -> int:
    """How long a projector must show each pattern for the cameras' current exposure (µs)."""
    return int(max(c.settings.exposure_us for c in cameras)) + DISPLAY_MARGIN_US


class CouplingError(DeviceError):
    """A frame cannot be proven to belong to the pattern it was acquired for."""


@dataclass
class AcquiredSequence:
    spec: dict[str, Any]
    #: camera name -> one frame per pattern, in pattern order
    frames: dict[str, list[Frame]]
    #: wall-clock ns at which each pattern was shown
    shown_ns: list[int]


async def acquire_sequence(projector: Projector, cameras: Sequence[Camera], spec: dict[str, Any],
                           timeout_s: float = 2.0) -> AcquiredSequence:
    """Load ``spec`` into the projector and acquire every pattern with every camera in
    hardware-trigger mode; the cameras' previous trigger mode is restored afterwards."""
    n = await projector.load_sequence(spec)
    previous = {cam.name: cam.settings.trigger for cam in cameras}
    frames: dict[str, list[Frame]] = {cam.name: [] for cam in cameras}
    shown: list[int] = []
    try:
        for cam in cameras:
            await cam.configure(trigger="hardware")
            await cam.flush()
        first_count: dict[str, int | None] = {}
        if projector.plays_sequences:
            await _played(projector, cameras, n, timeout_s, frames, shown, first_count)
            return AcquiredSequence(dict(spec), frames, shown)
        for k in range(n):
            t_k = now_ns()
            await projector.show(k)
            shown.append(t_k)
            for cam in cameras:
                frame = await _one_frame(cam, k, n, timeout_s)
                _check_frame(cam.name, frame, k, t_k, first_count)
                frames[cam.name].append(frame)
            for cam in cameras:
                extra = await cam.pending()
                if extra:
                    raise CouplingError(
                        f"{cam.name}: {extra} extra frame(s) after pattern {k} of {n}: the camera "
                        f"was triggered more than once per pattern (bouncing or shared trigger "
                        f"line); frames after pattern {k} cannot be assigned")
    finally:
        await projector.show(-1)
        for cam in cameras:
            try:
                await cam.flush()
            finally:
                await cam.configure(trigger=previous[cam.name])
    return AcquiredSequence(dict(spec), frames, shown)


async def _played(projector: Projector, cameras: Sequence[Camera], n: int, timeout_s: float,
                  frames: dict[str, list[Frame]], shown: list[int],
                  first_count: dict[str, int | None]) -> None:
    """A projector that plays the sequence itself: start it, then take each camera's n frames in
    trigger order; frame k is the k-th trigger after the start."""
    t0 = now_ns()
    await projector.play()
    shown.extend([t0] * n)
    for cam in cameras:
        for k in range(n):
            try:
                frame = await cam.grab(timeout_s)
            except Timeout as exc:
                raise CouplingError(
                    f"{cam.name}: {k} of {n} frames for the played sequence, none more within "
                    f"{timeout_s} s: a trigger pulse was lost (cable, trigger source or mode) "
                    f"[{exc}]") from None
            _check_frame(cam.name, frame, k, t0, first_count)
            frames[cam.name].append(frame)
    for cam in cameras:
        extra = await cam.pending()
        if extra:
            raise CouplingError(f"{cam.name}: {extra} extra frame(s) after the {n} patterns: the "
                                f"camera was triggered more than once per pattern")


async def _one_frame(cam: Camera, k: int, n: int, timeout_s: float) -> Frame:
    try:
        return await cam.grab(timeout_s)
    except Timeout as exc:
        raise CouplingError(
            f"{cam.name}: no frame for pattern {k} of {n} within {timeout_s} s: the projector's "
            f"trigger did not reach the camera (cable, trigger source or mode) [{exc}]") from None


def _check_frame(cam: str, frame: Frame, k: int, t_k: int,
                 first_count: dict[str, int | None]) -> None:
    if frame.stamp_ns < t_k:
        raise CouplingError(f"{cam}: the frame taken for pattern {k} was received before pattern "
                            f"{k} was shown: left over from an earlier trigger")
    if frame.trigger_count is None:
        return
    if k == 0:
        first_count[cam] = frame.trigger_count
        return
    base = first_count.get(cam)
    if base is not None and frame.trigger_count != base + k:
        raise CouplingError(f"{cam}: frame for pattern {k} carries trigger count "
                            f"{frame.trigger_count}, expected {base + k}: a trigger pulse was lost "
                            f"or doubled")
