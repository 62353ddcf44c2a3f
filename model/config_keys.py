"""How a cell config's keys are described where no dataclass holds them: each key's type,
default, unit and meaning. The parsers take their known keys from these tables, and the docs
site's config reference is generated from them (``docsgen/config_reference.py``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


class _Required:
    def __repr__(self) -> str:
        return "required"


#: the default of a key that must be given
REQUIRED: Any = _Required()


@dataclass(frozen=True)
class KeySpec:
    """One key of a config table. ``default`` None: absent means "not used"."""

    type: str
    doc: str
    default: Any = None
    unit: str = ""
