"""A job's final model put together from its parts on ``fusion/cloud``.

The fuse worker publishes a job's final model in parts (``meta.final``, ``meta.part`` from 0 of
``meta.parts``; ``workers/fuse.py`` ``publish_model``). A message without ``parts`` (a recording
made before the model came in parts) is a whole model.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class ModelPartsError(ValueError):
    """A part that does not fit the parts before it; names the job and the part."""


class ModelParts:
    """Each job's parts until its last one is in."""

    def __init__(self) -> None:
        self._jobs: dict[str, tuple[int, dict[int, np.ndarray]]] = {}

    def add(self, meta: dict[str, Any], points: np.ndarray) -> np.ndarray | None:
        """Take one final message's ``points`` (M, 3); the job's whole model (N, 3) once its
        every part is in, else None."""
        job = str(meta.get("job_id", "?"))
        parts, part = int(meta.get("parts", 1)), int(meta.get("part", 0))
        if not 0 <= part < parts:
            raise ModelPartsError(f"job {job}: part {part} of {parts}")
        expected, got = self._jobs.get(job, (parts, {}))
        if expected != parts:  # a job fused again (another fuse worker took it over): afresh
            got = {}
        got[part] = points
        if len(got) < parts:
            self._jobs[job] = (parts, got)
            return None
        self._jobs.pop(job, None)
        return np.concatenate([got[i] for i in range(parts)])

    def waiting(self) -> dict[str, tuple[int, int]]:
        """job -> (parts in, parts expected) of the models not yet whole."""
        return {job: (len(got), parts) for job, (parts, got) in self._jobs.items()}
