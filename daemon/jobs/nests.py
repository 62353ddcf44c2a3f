"""Drift control with the reference nests (``[metrology] nests``): measure them, report how far
they drifted, re-locate the tracker by best fit when the drift passes the tolerance, and stop
when they disagree beyond what a rigid re-location explains.

After the tracker is moved to another station of the plan, :meth:`DriftControl.locate` measures
the nests from there and solves every tracker set-up of the job together in one weighted bundle
(``analysis/tracker_network.py``, after SpatialAnalyzer's USMN): no chained best fits."""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from scancell.analysis.nest_fit import (
    NestGeometryError,
    fit_nests,
    nest_drift,
    off_by_more_than_a_turn,
    rough_location,
    turned_about_head,
)
from scancell.analysis.tracker_network import NetworkError, TrackerSigma, solve_network
from scancell.daemon.jobs.ecs_measure import averaged
from scancell.daemon.jobs.metrology import MetrologySettings
from scancell.devices.base import Tracker
from scancell.devices.errors import BeamBroken, DeviceError
from scancell.protocols.commands import CommandError

#: the chance a nest that did not move is called knocked, per reading
KNOCK_FALSE_ALARM = 1e-3
#: the residual of a nest that did not move is about Rayleigh-distributed in the plane across
#: the beam (the transverse sigma dominates the ADM's): P(r > k sigma) = exp(-k^2 / 2), so
#: k = sqrt(2 ln(1 / p))
KNOCK_SIGMAS = float(np.sqrt(2.0 * np.log(1.0 / KNOCK_FALSE_ALARM)))
#: FindReflector locks on a reflector within this angle of the direction it is given
#: (protocols/TRACKER_PROTOCOL.md)
FIND_CONE_DEG = 5.0
#: a set-up turned by eye is searched for its first nest in yaw steps of 2 (FIND_CONE_DEG - 1)
#: deg: neighbouring searches overlap by 2 deg, a margin for the head standing off the plan's
#: position (30 mm at 3 m turns a bearing by 0.6 deg)
YAW_SEARCH_STEP_DEG = 2.0 * (FIND_CONE_DEG - 1.0)
#: as far as a tripod turned by eye is searched, either way (deg): 3 steps
YAW_SEARCH_MAX_DEG = 3 * YAW_SEARCH_STEP_DEG
#: a reflector found by a searching set-up is the nest asked for only if some turn about the
#: head puts it within this of the nest's survey (mm): a tripod is set up within it of where
#: the plan (and the operator's prompt) puts its head
SET_UP_POSITION_TOLERANCE_MM = 200.0


def yaw_search_deg() -> list[float]:
    """The turns tried for a set-up's first nest, nearest first: 0, +8, -8, +16, ... deg."""
    steps = round(YAW_SEARCH_MAX_DEG / YAW_SEARCH_STEP_DEG)
    return [0.0] + [s * k * YAW_SEARCH_STEP_DEG for k in range(1, steps + 1) for s in (1, -1)]


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
        self.sigma = TrackerSigma()
        self.checks: list[dict[str, Any]] = []
        #: the tracker's set-ups in this job, in order (the first is where it stood at the
        #: start: the bundle's datum), each with the nests last measured from it (its frame)
        self.setups: dict[str, dict[str, np.ndarray]] = {}
        self.setup = "home"
        #: the first set-up's location in force (``T_world_from_tracker`` while it stood there)
        self._T_world_from_home = np.eye(4)
        #: 1-sigma (mm) of a moved set-up's location from the bundle, at the nests' range
        self._moved_sigma_mm: float | None = None

    @property
    def location_sigma_mm(self) -> float:
        """How well the tracker's location in force is known (mm): the last fit's RMS if that
        check re-located it, else the drift it allowed; unchecked: the stand's stability."""
        if not self.checks:
            return self.settings.unchecked_location_mm
        last = self.checks[-1]
        if last.get("moved"):
            return float(self._moved_sigma_mm or 0.0)
        if last["relocated"]:
            return float(last["fit_rms_mm"])
        return float(max(last["fit_rms_mm"], last["drift_max_mm"]))

    @property
    def moved(self) -> bool:
        """The tracker stands elsewhere than at the job's first set-up."""
        return bool(self.setups) and self.setup != next(iter(self.setups))

    @property
    def enabled(self) -> bool:
        return bool(self.survey)

    def to_world(self, point_mm: np.ndarray) -> np.ndarray:
        T = self.T_world_from_tracker
        return T[:3, :3] @ np.asarray(point_mm, float) + T[:3, 3]

    async def _measure_nest(self, name: str, label: str, T_guess: np.ndarray,
                            search: bool = False) -> tuple[np.ndarray | None, str]:
        """Find and measure nest ``name`` where ``T_guess`` (the set-up's location as known)
        puts it; a beam break is measured again once. ``search``: a set-up none of whose nests
        is found yet may be turned off the plan, so its yaw is searched (:func:`yaw_search_deg`)
        and a reflector is taken for the nest only where a turn of the set-up puts the nest."""
        survey = self.survey[name]
        why = ""
        for turn in yaw_search_deg() if search else [0.0]:
            T = turned_about_head(T_guess, turn)
            T_inv = np.linalg.inv(T)
            approx = T_inv[:3, :3] @ survey + T_inv[:3, 3]
            for attempt in range(2 if turn == 0.0 else 1):  # a beam break: once more
                try:
                    await self.tracker.find_reflector(approx)
                    p, _ = await averaged(self.tracker, self.settings.nest_repeats,
                                          {**self.meta, "nest": name, "check": label,
                                           "attempt": attempt,
                                           **({"yaw_search_deg": turn} if turn else {})})
                except (BeamBroken, DeviceError, CommandError) as exc:
                    why = exc.message if isinstance(exc, CommandError) else str(exc)
                    continue
                off = off_by_more_than_a_turn(T, p, survey)
                if not search or off <= SET_UP_POSITION_TOLERANCE_MM:
                    return p, ""
                why = (f"the reflector found {turn:+g} deg off the set-up's bearing is "
                       f"{off:.0f} mm off the nest however the set-up is turned")
                break
        if search:
            why = f"not found within +-{YAW_SEARCH_MAX_DEG:g} deg of the plan's bearing: {why}"
        return None, why

    async def _measure_all(self, label: str, return_to_mm: np.ndarray | None,
                           set_up: bool = False
                           ) -> tuple[dict[str, np.ndarray], dict[str, str]]:
        """Every nest (one out of sight is tried twice, then left out), then the beam back on
        ``return_to_mm`` (tracker frame); NestCheckFailed if fewer than ``min_nests``. A new
        ``set_up`` is known only roughly: its first nest is searched in yaw, and each nest found
        corrects where the next is looked for (:func:`rough_location`)."""
        measured: dict[str, np.ndarray] = {}
        missing: dict[str, str] = {}
        T_guess = self.T_world_from_tracker
        try:
            for name in self.survey:
                p, why = await self._measure_nest(name, label, T_guess,
                                                  search=set_up and not measured)
                if p is None:
                    missing[name] = why
                    continue
                measured[name] = p
                if set_up:
                    T_guess = rough_location(T_guess, self.survey, measured)
        finally:
            if return_to_mm is not None:
                with contextlib.suppress(Exception):
                    await self.tracker.find_reflector(return_to_mm)
        s = self.settings
        if len(measured) < s.min_nests:
            raise NestCheckFailed(
                f"nest check {label}: {len(measured)} of {len(self.survey)} nests measured, "
                f"{s.min_nests} needed; out of sight: "
                + "; ".join(f"{n} ({w})" for n, w in missing.items()))
        self.setups[self.setup] = measured
        return measured, missing

    async def check(self, label: str, return_to_mm: np.ndarray | None) -> dict[str, Any]:
        """Measure every nest (a nest out of sight is tried twice, then left out), then lock
        the tracker on ``return_to_mm`` (tracker frame) again. Returns the check's record;
        NestCheckFailed if fewer than ``min_nests`` answered or they disagree. On a set-up the
        tracker was moved to, the check solves the network again (:meth:`locate`); its drift is
        how far each nest reads from its reading when the set-up was last located (mm)."""
        if self.moved:
            before = self.setups[self.setup]
            record = await self.locate(self.setup, self.T_world_from_tracker, label, return_to_mm)
            now = self.setups[self.setup]
            drift = {n: float(np.linalg.norm(now[n] - before[n])) for n in now if n in before}
            record.update(drift_mm={n: round(v, 5) for n, v in drift.items()},
                          drift_max_mm=round(max(drift.values(), default=0.0), 5))
            return record
        measured, missing = await self._measure_all(label, return_to_mm)
        s = self.settings
        try:
            fit = fit_nests(self.survey, measured)
        except NestGeometryError as exc:
            raise NestCheckFailed(f"nest check {label}: {exc}") from None
        worst, off, limit = self._worst_fit(
            {n: (r, measured[n]) for n, r in fit.residual_mm.items()})
        if off > limit:
            raise NestCheckFailed(
                f"nest check {label}: the nests disagree: {worst} is {off:.3f} mm off the others' "
                f"best fit (limit {limit:.3f} mm at its range); was it knocked, or did "
                f"the tracker move?")
        drift = nest_drift(self.survey, measured, self.T_world_from_tracker)
        relocated = max(drift.values()) > s.drift_tolerance_mm
        if relocated:
            self.T_world_from_tracker = fit.T_world_from_tracker
            self._T_world_from_home = fit.T_world_from_tracker
        record = {"check": label, "nests": sorted(measured), "missing": missing,
                  "drift_mm": {n: round(v, 5) for n, v in drift.items()},
                  "drift_max_mm": round(max(drift.values()), 5),
                  "fit_rms_mm": round(fit.rms_mm, 5), "relocated": relocated,
                  "T_world_from_tracker": self.T_world_from_tracker.tolist()}
        self.checks.append(record)
        return record

    def knock_limit_mm(self, p_tracker: np.ndarray) -> float:
        """How far (mm) a nest read at ``p_tracker`` (tracker frame, mm) may sit off the fit
        before it is called knocked: ``nest_fit_tolerance_mm``, or the tracker's own noise at
        that range (KNOCK_SIGMAS x its transverse 1-sigma) where that is larger; a far nest
        cannot be held to a tolerance the tracker cannot resolve there."""
        _, s_t = self.sigma.sigmas_mm(float(np.linalg.norm(p_tracker)))
        return max(self.settings.nest_fit_tolerance_mm, KNOCK_SIGMAS * s_t)

    def _worst_fit(self, residuals: dict[Any, tuple[float, np.ndarray]]
                   ) -> tuple[Any, float, float]:
        """(key, residual mm, limit mm) of the reading furthest past its limit, from
        ``key -> (residual mm, reading in the tracker frame mm)``."""
        limits = {k: self.knock_limit_mm(p) for k, (_, p) in residuals.items()}
        key = max(residuals, key=lambda k: residuals[k][0] / limits[k])
        return key, residuals[key][0], limits[key]

    async def locate(self, setup: str, T_rough: np.ndarray, label: str,
                     return_to_mm: np.ndarray | None = None) -> dict[str, Any]:
        """The tracker stands at a new set-up ``setup``, roughly at ``T_rough``
        (``T_world_from_tracker`` of its readings, from the plan): measure the nests from there
        (found at their predicted positions) and solve every set-up of the job in one weighted
        bundle, the first set-up the datum. The set-up's location becomes the one in force.
        NestCheckFailed names a nest that fits the network worse than ``nest_fit_tolerance_mm``
        (knocked?), or too few nests in common with the set-ups before."""
        if not self.setups:
            raise NestCheckFailed(f"nest check {label}: the nests were not measured where the "
                                  f"tracker stood first; a move cannot be tied to the cell")
        self.setup = setup
        self.T_world_from_tracker = np.asarray(T_rough, float)
        measured, missing = await self._measure_all(label, return_to_mm, set_up=True)
        order = list(self.setups)
        try:
            net = solve_network(self.setups, TrackerSigma(), order)
        except NetworkError as exc:
            raise NestCheckFailed(f"nest check {label}: {exc}") from None
        (worst_setup, worst_nest), off, limit = self._worst_fit(
            {(st, n): (r, self.setups[st][n]) for (st, n), r in net.residual_mm.items()})
        if off > limit:
            raise NestCheckFailed(
                f"nest check {label}: nest {worst_nest} does not fit the tracker network: "
                f"{off:.3f} mm off from set-up {worst_setup} (limit {limit:.3f} mm at its "
                f"range); was it knocked?")
        self.T_world_from_tracker = self._T_world_from_home @ net.stations[setup]
        sig = net.station_sigma(setup)
        lever = float(np.mean([np.linalg.norm(p) for p in measured.values()]))
        self._moved_sigma_mm = float(np.hypot(
            sig["translation_mm"], np.radians(sig["rotation_arcsec"] / 3600.0) * lever))
        rms = float(np.sqrt(np.mean([net.residual_mm[(setup, n)] ** 2 for n in measured])))
        record = {"check": label, "tracker_station": setup, "moved": True,
                  "nests": sorted(measured), "missing": missing,
                  "drift_mm": {}, "drift_max_mm": 0.0,
                  "fit_rms_mm": round(rms, 5), "relocated": True,
                  "network": {"setups": order, "variance_factor": round(net.variance_factor, 3),
                              "sigma_translation_mm": round(sig["translation_mm"], 5),
                              "sigma_rotation_arcsec": round(sig["rotation_arcsec"], 3),
                              "sigma_at_nests_mm": round(self._moved_sigma_mm, 5),
                              "worst": {"setup": worst_setup, "nest": worst_nest,
                                        "residual_mm": round(off, 5)}},
                  "T_world_from_tracker": self.T_world_from_tracker.tolist()}
        self.checks.append(record)
        return record
