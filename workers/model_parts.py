"""A job's final model put together from its parts on ``fusion/cloud``.

The fuse worker publishes a job's final model in parts (``meta.final``, ``meta.part`` from 0 of
``meta.parts``; ``workers/fuse.py`` ``publish_model``). A message without ``parts`` (a recording
made before the model came in parts) is a whole model.
"""

from __future__ import annotations

from itertools import pairwise
from typing import Any

import numpy as np


class ModelPartsError(ValueError):
    """A part that does not fit the parts before it; names the job and the part."""


class _Job:
    """One job's model as its parts come in: copied into the whole model's array at once when
    the meta names the model's size (``points``), else kept until the last part."""

    def __init__(self, job: str, parts: int, total: int | None) -> None:
        self.job, self.parts, self.total = job, parts, total
        self.got: dict[int, np.ndarray | slice] = {}
        self.whole: np.ndarray | None = None
        self.part_size: int | None = None

    def add(self, part: int, points: np.ndarray) -> None:
        if self.total is None:
            self.got[part] = points
            return
        n = len(points)
        last = part == self.parts - 1
        if not last:  # every part but the last holds the same count (publish_model)
            if self.part_size is not None and n != self.part_size:
                raise ModelPartsError(f"job {self.job}: part {part} has {n} points, the parts "
                                      f"before it {self.part_size}")
            self.part_size = n
        start = self.total - n if last else part * n
        if start < 0 or start + n > self.total:
            raise ModelPartsError(f"job {self.job}: part {part} of {self.parts} ({n} points) "
                                  f"does not fit a model of {self.total}")
        if self.whole is None:
            self.whole = np.empty((self.total, *points.shape[1:]), points.dtype)
        self.whole[start:start + n] = points
        self.got[part] = slice(start, start + n)

    def model(self) -> np.ndarray:
        if self.total is None:
            return np.concatenate([self.got[i] for i in range(self.parts)])
        spans = sorted((s.start, s.stop) for s in self.got.values())
        if spans[0][0] != 0 or spans[-1][1] != self.total or any(
                a[1] != b[0] for a, b in pairwise(spans)):
            raise ModelPartsError(f"job {self.job}: its {self.parts} parts do not tile a model "
                                  f"of {self.total} points")
        assert self.whole is not None
        return self.whole


class ModelParts:
    """Each job's parts until its last one is in. When the meta names the model's size, each
    part goes straight into the model's array: the model is held once, never twice."""

    def __init__(self) -> None:
        self._jobs: dict[str, _Job] = {}

    def add(self, meta: dict[str, Any], points: np.ndarray) -> np.ndarray | None:
        """Take one final message's ``points`` (M, 3), or (M, C) with more columns per point;
        the job's whole model (N, 3 or C) once its every part is in, else None."""
        job = str(meta.get("job_id", "?"))
        parts, part = int(meta.get("parts", 1)), int(meta.get("part", 0))
        if not 0 <= part < parts:
            raise ModelPartsError(f"job {job}: part {part} of {parts}")
        total = int(meta["points"]) if "points" in meta else None
        held = self._jobs.get(job)
        if held is None or (held.parts, held.total) != (parts, total):
            held = _Job(job, parts, total)  # new, or fused again (another fuse worker): afresh
        try:
            held.add(part, points)
        except ModelPartsError:
            self._jobs.pop(job, None)
            raise
        if len(held.got) < parts:
            self._jobs[job] = held
            return None
        self._jobs.pop(job, None)
        return held.model()

    def waiting(self) -> dict[str, tuple[int, int]]:
        """job -> (parts in, parts expected) of the models not yet whole."""
        return {job: (len(h.got), h.parts) for job, h in self._jobs.items()}
