"""Choosing a simulation profile (optics, mechanics): a named set of parameters, with whole
effects switched back to the ideal and single fields overridden."""

from __future__ import annotations

from dataclasses import fields, replace
from typing import TypeVar

P = TypeVar("P")


class ProfileError(ValueError):
    """An unknown profile, effect or parameter, named."""


def select_profile(kind: str, profiles: dict[str, P], effects: dict[str, tuple[str, ...]],
                   name: str, effects_off: tuple[str, ...] | list[str],
                   overrides: dict[str, object]) -> P:
    """``profiles[name]`` with each effect of ``effects_off`` at the ``"ideal"`` profile's
    values and ``overrides`` applied; ProfileError names what is unknown (``kind``: "optics",
    "mechanics")."""
    if name not in profiles:
        raise ProfileError(f"unknown {kind} profile {name!r}: one of {sorted(profiles)}")
    p, ideal = profiles[name], profiles["ideal"]
    for effect in effects_off:
        if effect not in effects:
            raise ProfileError(f"unknown {kind} effect {effect!r}: one of {sorted(effects)}")
        p = replace(p, **{f: getattr(ideal, f) for f in effects[effect]})
    known = {f.name for f in fields(p)}
    for key in overrides:
        if key not in known or key == "name":
            raise ProfileError(f"unknown {kind} parameter {key!r}")
    return replace(p, **overrides) if overrides else p
