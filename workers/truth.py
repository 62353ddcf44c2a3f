"""Ground truth for the true-error figures: the simulated part's distance function, from a cell
config's or a recording's ``[simulator]`` table. The simulator is reached by name
(``scancell.devices.simulator``), never imported."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

Truth = Callable[[np.ndarray], np.ndarray]


def truth_from_options(options: dict[str, Any]) -> Truth:
    """World points (mm) -> distance (mm) to the simulated part a ``[simulator]`` table holds."""
    from scancell.devices.simulator import load_simulator

    return load_simulator().truth(options)


def truth_from_config(path: str | Path) -> Truth:
    """The same for the simulated cell a config file describes; raises ValueError naming the
    file (no such config, no ``[simulator]``)."""
    from scancell.config import ConfigError, load_cell_config

    try:
        cfg = load_cell_config(path)
    except ConfigError as exc:
        raise ValueError(str(exc)) from None
    if cfg.simulator is None:
        raise ValueError(f"{path} has no [simulator]: no ground truth")
    return truth_from_options(cfg.simulator)
