"""Real captures: SLStudio's example data (one camera, one projector, codec "2x3"), read in
place from ../shared/data/realfringe/slstudio (GPLv3 data, never copied into this repository).

The figures the issue on real scanners asks (benchmarks/bench_real_captures.py prints them all):
boards ≥ 90 % decoded inside their outer corners, flat to ≤ 0.20 mm RMS on every pose and
≤ 0.15 mm as the median; the skull ≥ 350 k points within a median 0.30 mm of SLStudio's own
Gray-code cloud."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scancell.analysis.board_check import check_board
from scancell.analysis.cloud_io import read_ply
from scancell.analysis.metrics import local_plane_distance
from scancell.analysis.pattern_decode import decode_view
from scancell.analysis.pattern_files import find_frames, read_frames
from scancell.analysis.projector_rig import read_rig
from scancell.analysis.projector_scan import reconstruct
from scancell.analysis.stereo_calibration import ChessboardSpec
from scancell.model.pattern_set import preset

from .conftest import SLSTUDIO_DATA as DATA

BOARD = ChessboardSpec(13, 9, 10.0)
POSES = ("calseq1", "calseq3", "calseq4", "calseq6")

pytestmark = pytest.mark.skipif(
    not DATA.is_dir(), reason=f"{DATA} is not beside this checkout (or SCANCELL_SHARED_DATA)")


@pytest.fixture(scope="module")
def rig():
    return read_rig(DATA / "calibration" / "calibration.xml")


@pytest.mark.unit
def test_board_poses_decode_flat(rig):
    spec = preset("slstudio-2x3")
    flatness = []
    for pose in POSES:
        frames, names = read_frames(find_frames(DATA / "calibration" / pose, spec))
        view = decode_view(frames, spec, rig.projector_size, names=names)
        cloud = reconstruct(rig, view)
        check = check_board(cloud.points, cloud.pixels, view.background, rig.K_cam, rig.D_cam, BOARD)
        assert check.coverage >= 0.90, (pose, check)
        assert check.flatness_rms_mm <= 0.20, (pose, check)
        # the corners' own plane (solvePnP) agrees to within the calibration's accuracy
        assert abs(check.pnp_offset_mm) < 1.0, (pose, check)
        flatness.append(check.flatness_rms_mm)
    assert np.median(flatness) <= 0.15, flatness


@pytest.mark.process
def test_skull_through_the_documented_command(tmp_path):
    """`scancell decode --calib calibration.xml --patterns slstudio-2x3 --images skull_2x3`."""
    from scipy.io import loadmat
    from scipy.spatial import cKDTree

    out = tmp_path / "skull.ply"
    r = subprocess.run([sys.executable, "-m", "scancell", "decode", "--calib",
                        str(DATA / "calibration" / "calibration.xml"), "--patterns", "slstudio-2x3",
                        "--images", str(DATA / "skull_2x3"), "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "warning" not in r.stderr.lower()  # the 1-period cue raises no false response alarm
    points, fields = read_ply(out)
    assert len(points) >= 350_000
    assert {"quality", "intensity", "uncertainty"} <= set(fields)
    ref = loadmat(DATA / "skull_gray" / "pointCloud.mat")["xyz"].reshape(-1, 3)
    ref = ref[np.isfinite(ref).all(1)]
    dist, _ = cKDTree(ref).query(points, workers=2)
    assert np.median(dist) <= 0.30
    # against the Gray-code surface (a local plane through its stripe edges within 3 mm):
    # unsupported <= 3 % (the figure); beyond 1 mm of it 1.0 % today (0.5 % asked: not
    # met, benchmarks/RESULTS.md), held from growing
    plane, supported = local_plane_distance(points.astype(float), ref, reach_mm=3.0)
    assert 1 - supported.mean() <= 0.03
    assert np.median(plane[supported]) <= 0.15 and np.mean(plane[supported] > 1.0) <= 0.012
    header = out.read_bytes()[:800].decode("ascii", "replace")
    assert "comment frame: camera" in header and "slstudio-2x3" in header
