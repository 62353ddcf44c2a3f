"""Drift control with the reference nests (``[metrology] nests``): measure them, report how far
they drifted, re-locate the tracker by best fit when the drift passes the tolerance, and stop
when they disagree beyond what a rigid re-location explains."""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from scancell.analysis.nest_fit import NestGeometryError, fit_nests, nest_drift
from scancell.daemon.jobs.ecs_measure import averaged
from scancell.daemon.jobs.metrology import MetrologySettings
from scancell.devices.base import Tracker
from scancell.devices.errors import BeamBroken, DeviceError
from scancell.protocols.commands import CommandError


class NestCheckFailed(CommandError):
    def __init__(self, message: str) -> None:
        super().__init__("nest_check_failed", message)


class DriftControl:
    """The tracker's location in ``world`` over a job, kept by nest checks.

    ``T_world_from_tracker`` is the location in force: identity until the first check that sees
    drift beyond the tolerance, then the last best fit."""

    def __init__(self, tracker: Tracker, settings: MetrologySettings, meta: dict[str, Any]) -> None:
        self.tracker = tracker
        self.settings = settings
        self.meta = meta
        self.survey = {n: np.asarray(p, float) for n, p in settings.nests.items()}
        self.T_world_from_tracker = np.eye(4)
        self.checks: list[dict[str, Any]] = []

    @property
    def location_sigma_mm(self) -> float:
        """How well the tracker's location in force is known (mm): the last fit's RMS if that
        check re-located it, else the drift it allowed; unchecked: the stand's stability."""
        if not self.checks:
            return self.settings.unchecked_location_mm
        last = self.checks[-1]
        if last["relocated"]:
            return float(last["fit_rms_mm"])
        return float(max(last["fit_rms_mm"], last["drift_max_mm"]))

    @property
    def enabled(self) -> bool:
        return bool(self.survey)

    def to_world(self, point_mm: np.ndarray) -> np.ndarray:
        T = self.T_world_from_tracker
        return T[:3, :3] @ np.asarray(point_mm, float) + T[:3, 3]

    async def _measure_nest(self, name: str, label: str) -> tuple[np.ndarray | None, str]:
        T_inv = np.linalg.inv(self.T_world_from_tracker)
        approx = T_inv[:3, :3] @ self.survey[name] + T_inv[:3, 3]
        why = ""
        for attempt in range(2):  # a beam break is measured again once
            try:
                await self.tracker.find_reflector(approx)
                p, _ = await averaged(self.tracker, self.settings.nest_repeats,
                                      {**self.meta, "nest": name, "check": label,
                                       "attempt": attempt})
                return p, ""
            except (BeamBroken, DeviceError, CommandError) as exc:
                why = exc.message if isinstance(exc, CommandError) else str(exc)
        return None, why

    async def check(self, label: str, return_to_mm: np.ndarray) -> dict[str, Any]:
        """Measure every nest (a nest out of sight is tried twice, then left out), then lock
        the tracker on ``return_to_mm`` (tracker frame) again. Returns the check's record;
        NestCheckFailed if fewer than ``min_nests`` answered or they disagree."""
        measured: dict[str, np.ndarray] = {}
        missing: dict[str, str] = {}
        try:
            for name in self.survey:
                p, why = await self._measure_nest(name, label)
                if p is None:
                    missing[name] = why
                else:
                    measured[name] = p
        finally:
            with contextlib.suppress(Exception):
                await self.tracker.find_reflector(return_to_mm)
        s = self.settings
        if len(measured) < s.min_nests:
            raise NestCheckFailed(
                f"nest check {label}: {len(measured)} of {len(self.survey)} nests measured, "
                f"{s.min_nests} needed; out of sight: "
                + "; ".join(f"{n} ({w})" for n, w in missing.items()))
        try:
            fit = fit_nests(self.survey, measured)
        except NestGeometryError as exc:
            raise NestCheckFailed(f"nest check {label}: {exc}") from None
        worst, off = fit.worst
        if off > s.nest_fit_tolerance_mm:
            raise NestCheckFailed(
                f"nest check {label}: the nests disagree: {worst} is {off:.3f} mm off the others' "
                f"best fit (tolerance {s.nest_fit_tolerance_mm:g} mm); was it knocked, or did "
                f"the tracker move?")
        drift = nest_drift(self.survey, measured, self.T_world_from_tracker)
        relocated = max(drift.values()) > s.drift_tolerance_mm
        if relocated:
            self.T_world_from_tracker = fit.T_world_from_tracker
        record = {"check": label, "nests": sorted(measured), "missing": missing,
                  "drift_mm": {n: round(v, 5) for n, v in drift.items()},
                  "drift_max_mm": round(max(drift.values()), 5),
                  "fit_rms_mm": round(fit.rms_mm, 5), "relocated": relocated,
                  "T_world_from_tracker": self.T_world_from_tracker.tolist()}
        self.checks.append(record)
        return record
