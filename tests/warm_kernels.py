"""Compile every numba kernel once, before the test processes start.

The kernels are cached on disk (``cache=True``, next to their modules), but a fresh clone has
no cache: every daemon, worker and xdist process that starts before a kernel's first
compilation ends compiles it again, side by side on 2 cores. ``tests/conftest.py`` runs this in
pytest's controller process, once, before the xdist workers start.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np


def warm() -> None:
    from scancell.analysis.metrics import compare_clouds
    from scancell.analysis.scanner import ScanDecoder
    from scancell.analysis.stereo_calibration import StereoCalibration
    from scancell.model.patterns import FringeSequence
    from scancell.sim.cell import SimCell, SimCellConfig
    from scancell.sim.optics_profile import optics_profile

    ideal = SimCell(SimCellConfig(camera_scale=16, optics=optics_profile("ideal")))
    ideal.load_sequence(FringeSequence())
    ideal.render("left", 0)  # its sensor: the other quantiser
    cell = SimCell(SimCellConfig(camera_scale=16))
    target = cell.cfg.T_world_from_part[:3, 3] + [-200.0, 0.0, 0.0]
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(target, 600.0)))
    cell.load_sequence(FringeSequence())
    left, right = cell.render_sequence("left"), cell.render_sequence("right")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "stereo.yaml"
        cell.rig.write_opencv_yaml(path)
        decoder = ScanDecoder(StereoCalibration.read(path), FringeSequence())
        decoder.decode(left, right)
        decoder.decode_exposures([left, left], [right, right])
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 50, (4000, 3)) * [1, 1, 0]
    compare_clouds({"a": a, "b": a + np.array([0.01, 0.0, 0.0])})


if __name__ == "__main__":
    warm()
