"""Conformance decided with the measurement's uncertainty (ISO 14253-1:2017, guard bands).

A measured value ``y`` with expanded uncertainty ``U`` (k = 2) against the specification zone
``[lower, upper]``:

- conformance is proven when ``lower + U <= y <= upper - U`` (the acceptance zone);
- non-conformance is proven when ``y < lower - U`` or ``y > upper + U`` (the rejection zone);
- in between neither is proven: the verdict is ``not provable``.

Rule ``simple`` takes U as 0 (shared risk: the zone's edge decides), the verdict before this
module existed. A zone no wider than ``2 U`` has no acceptance zone: nothing can be proven to
conform there, and the verdict says why.

A surface region is judged point by point (each point's deviation against its own U) and by
its share: it passes while the points not proven inside are at most the allowed share and no
defect is proven; it fails when the points proven outside exceed the share or a defect's height
is proven beyond the zone; otherwise it is not provable.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

RULES = ("iso14253-1", "simple")
DEFAULT_RULE = "iso14253-1"

PASS, FAIL, NOT_PROVABLE, NOT_MEASURED = "pass", "fail", "not provable", "not measured"
VERDICTS = (PASS, FAIL, NOT_PROVABLE, NOT_MEASURED)

#: coverage factor of every expanded uncertainty stated (about 95 % for a normal error)
K = 2.0


class DecisionError(ValueError):
    """An unknown rule or an uncertainty that is not a finite number >= 0."""


def check_rule(rule: str) -> str:
    if rule not in RULES:
        raise DecisionError(f"decision rule {rule!r} unknown: use one of {', '.join(RULES)}")
    return rule


@dataclass(frozen=True)
class Zone:
    """The specification zone (mm); ``lower < upper``."""

    lower: float
    upper: float


def guard(U: np.ndarray | float, rule: str) -> np.ndarray | float:
    """The guard band the rule applies: U (iso14253-1) or 0 (simple)."""
    return 0.0 * np.asarray(U) if check_rule(rule) == "simple" else U


def decide(value: float, U: float, zone: Zone, rule: str = DEFAULT_RULE) -> str:
    """The verdict on one value (mm) with its expanded uncertainty ``U`` (mm)."""
    if not np.isfinite(value):
        return NOT_MEASURED
    if not (np.isfinite(U) and U >= 0):
        raise DecisionError(f"expanded uncertainty {U!r}: must be a finite number >= 0")
    g = float(guard(U, rule))
    if zone.lower + g <= value <= zone.upper - g:
        return PASS
    if value < zone.lower - g or value > zone.upper + g:
        return FAIL
    return NOT_PROVABLE


def classify(deviation: np.ndarray, U: np.ndarray | float, zone: Zone, rule: str
             ) -> tuple[np.ndarray, np.ndarray]:
    """Per point: (proven inside, proven outside), two bool arrays."""
    d = np.asarray(deviation)
    g = np.asarray(guard(U, rule), d.dtype if d.dtype.kind == "f" else float)
    inside = (d >= zone.lower + g) & (d <= zone.upper - g)
    outside = (d < zone.lower - g) | (d > zone.upper + g)
    return inside, outside


def share_verdict(not_inside_share: float, outside_share: float, allowed_share: float,
                  defect_verdicts: list[str]) -> str:
    """The verdict of a region judged by its points' share and its defects."""
    if outside_share > allowed_share or FAIL in defect_verdicts:
        return FAIL
    if not_inside_share <= allowed_share and all(v == PASS for v in defect_verdicts):
        return PASS
    return NOT_PROVABLE


def combine(verdicts: list[str]) -> str:
    """The verdict of several characteristics: any fail fails; all pass passes; otherwise
    not provable. Characteristics not measured do not count, unless none was measured."""
    measured = [v for v in verdicts if v != NOT_MEASURED]
    if not measured:
        return NOT_MEASURED
    if FAIL in measured:
        return FAIL
    return PASS if all(v == PASS for v in measured) else NOT_PROVABLE


def as_pass(verdict: str) -> bool | None:
    """The boolean ``pass`` beside a verdict: true only when conformance is proven, false
    otherwise, None when nothing was measured."""
    return None if verdict == NOT_MEASURED else verdict == PASS


def no_acceptance_zone(zone: Zone, U: float, rule: str) -> str | None:
    """Why nothing can be proven to conform in ``zone`` with the typical ``U`` (mm), or None."""
    if check_rule(rule) == "simple" or zone.upper - zone.lower > 2 * U:
        return None
    return (f"the tolerance zone {zone.lower:+g} .. {zone.upper:+g} mm is no wider than twice "
            f"the measurement's expanded uncertainty U = {U:.3f} mm (k = 2): ISO 14253-1 "
            f"leaves no acceptance zone, so conformance cannot be proven")


def describe(rule: str) -> dict[str, Any]:
    """The rule as reports state it."""
    if check_rule(rule) == "simple":
        return {"rule": rule, "k": K, "text": "simple acceptance: the tolerance zone's edge "
                                             "decides; the uncertainty is stated, not applied"}
    return {"rule": rule, "k": K, "text": "ISO 14253-1: conformance proven inside the tolerance "
                                         "less U, non-conformance beyond the tolerance plus U, "
                                         "not provable in between"}
