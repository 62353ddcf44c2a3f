"""The scanner check's figures from one scan of a calibrated ball bar (scanner frame, mm): the
bar's length error and the scale it means (ppm), and the spheres' form (VDI/VDE 2634-2 PF)
and size error, against the warning limits."""

from __future__ import annotations

from typing import Any

import numpy as np
from scancell.analysis.vdi2634 import AcceptanceError, probing, sphere_spacing


class CheckError(ValueError):
    """The scan does not show the ball bar well enough to judge the scanner."""


def evaluate_check(points_mm: np.ndarray, length_mm: float, sphere_diameter_mm: float,
                   warn_ppm: float, warn_form_mm: float, sigma_mm: np.ndarray | None = None
                   ) -> dict[str, Any]:
    """Length error (mm), scale (ppm), form and size error of the two spheres (mm), and the
    ``warnings`` of the limits passed. With the points' stated noise ``sigma_mm`` also
    ``form_noise_mm``: the form that noise alone gives the worse sphere's points. CheckError
    when the bar is not found."""
    pts = np.asarray(points_mm, float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 50:
        raise CheckError(f"{len(pts)} points: too few to find the ball bar")
    if sigma_mm is not None and np.shape(sigma_mm) != (len(pts),):
        raise CheckError(f"{np.shape(sigma_mm)} noise figures for {len(pts)} points")
    try:
        sd = sphere_spacing(pts, length_mm, sphere_diameter_mm)
        spheres = [probing(pts, sphere_diameter_mm, np.asarray(c), sigma_mm)
                   for c in sd["centres_mm"]]
    except AcceptanceError as exc:
        raise CheckError(str(exc)) from None
    scale_ppm = sd["SD"] / length_mm * 1e6
    worst = max(spheres, key=lambda s: s["PF"])
    form = worst["PF"]
    size = max((s["PS"] for s in spheres), key=abs)
    out: dict[str, Any] = {
        "length_mm": round(sd["length_mm"], 5), "length_error_mm": round(sd["SD"], 5),
        "scale_ppm": round(scale_ppm, 1), "form_mm": round(form, 5),
        "size_error_mm": round(size, 5), "points": [s["points"] for s in spheres],
        "warnings": []}
    if "PF_noise" in worst:
        out["form_noise_mm"] = round(worst["PF_noise"], 5)
    if abs(scale_ppm) > warn_ppm:
        out["warnings"].append(f"scale {scale_ppm:+.0f} ppm beyond +/-{warn_ppm:g} ppm: the "
                               f"stereo calibration has drifted (recalibrate, or let the "
                               f"scanner warm up)")
    if form > warn_form_mm:
        noise = (f" (its points' noise alone gives {out['form_noise_mm']:.3f} mm)"
                 if "form_noise_mm" in out else "")
        out["warnings"].append(f"sphere form {form:.3f} mm beyond {warn_form_mm:g} mm{noise}")
    return out
