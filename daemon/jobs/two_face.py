"""``cmd/job/two_face``: the tracker's two-face check (ASME B89.4.19 / ISO 10360-10 practice).

Each reference nest (``[metrology.nests]``, or those the request names) is measured in the
front face and in the back face. A tracker's odd geometric errors (encoder eccentricity, vertical
index, beam offset) change sign between the faces, so the distance between the two readings is
twice their effect there. The report names each nest's two-face error beside the tolerance: by
default the tracker's angular MPE at that range, ±(15 µm + 6 µm/m), for each face."""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from scancell.daemon.jobs.devices import serving_device
from scancell.daemon.jobs.ecs_measure import averaged
from scancell.daemon.jobs.runner import JobContext, StepFailed
from scancell.daemon.supervision.supervisor import DeviceSupervisor, hold_for_job
from scancell.devices.base import Tracker
from scancell.devices.errors import DeviceError
from scancell.model.metrology_settings import MetrologySettings
from scancell.protocols.commands import CommandError

VERB = "two_face"


def angular_mpe_mm(range_mm: float) -> float:
    """The transverse MPE of ISO 10360-10-style tracker specifications (mm)."""
    return (15.0 + 6.0 * range_mm / 1000.0) / 1000.0


def nests_to_check(req: dict[str, Any], metrology: MetrologySettings) -> list[str]:
    """The nests a request names (default: all of the cell's); CommandError if none or unknown."""
    names = list(req.get("nests") or metrology.nests)
    if not names:
        raise CommandError("invalid", "two_face: no nests: the cell config has no "
                                      "[metrology.nests] and the request names none")
    unknown = sorted(set(names) - set(metrology.nests))
    if unknown:
        raise CommandError("invalid", f"two_face: unknown nests {unknown} (known: "
                                      f"{sorted(metrology.nests)})")
    return names


async def two_face(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                   metrology: MetrologySettings) -> dict[str, Any]:
    req = ctx.request
    names = nests_to_check(req, metrology)
    repeats = int(req.get("repeats", metrology.nest_repeats))
    tracker_s = serving_device(supervisors, req.get("tracker"), Tracker, VERB)
    tracker: Tracker = tracker_s.device
    rows: list[dict[str, Any]] = []
    async with contextlib.AsyncExitStack() as stack:
        await hold_for_job(stack, ctx.job_id, [tracker_s])
        home = None
        with contextlib.suppress(DeviceError):
            home = (await tracker.measure()).point_mm  # to lock on the scanner again
        try:
            for i, name in enumerate(names):
                ctx.event("running", "nest", f"two-face check: {name} ({i + 1}/{len(names)})",
                          i, len(names))
                survey = np.asarray(metrology.nests[name], float)
                try:
                    await tracker.find_reflector(survey)
                    meta = {"job_id": ctx.job_id, "nest": name}
                    front, _ = await averaged(tracker, repeats, {**meta, "face": 1})
                    await tracker.set_face(2)
                    back, _ = await averaged(tracker, repeats, {**meta, "face": 2})
                    await tracker.set_face(1)
                except (DeviceError, CommandError) as exc:
                    why = exc.message if isinstance(exc, CommandError) else str(exc)
                    raise StepFailed(name, "two_face", why) from exc
                rng = float(np.linalg.norm((front + back) / 2))
                tol = float(req.get("tolerance_mm", 2 * angular_mpe_mm(rng)))
                err = float(np.linalg.norm(front - back))
                rows.append({"nest": name, "range_mm": round(rng, 1),
                             "front_mm": front.round(4).tolist(), "back_mm": back.round(4).tolist(),
                             "two_face_mm": round(err, 5), "tolerance_mm": round(tol, 5),
                             "pass": err <= tol})
        finally:
            with contextlib.suppress(Exception):
                await tracker.set_face(1)
            if home is not None:
                with contextlib.suppress(Exception):
                    await tracker.find_reflector(home)
    worst = max(rows, key=lambda r: r["two_face_mm"] / r["tolerance_mm"])
    return {"nests": rows, "worst": worst["nest"], "two_face_max_mm": max(
        r["two_face_mm"] for r in rows), "pass": all(r["pass"] for r in rows)}
