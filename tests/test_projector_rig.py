"""Camera-projector rigs against the simulated rig's truth (sim/projector_rig_sim.py): every
pattern kind decodes to the true projector coordinates and the true plane; the rig is
calibrated from phase maps of a checkerboard; and the CLI refuses bad input without writing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scancell.analysis.cloud_io import read_ply
from scancell.analysis.decode_limits import DecodeLimits
from scancell.analysis.pattern_decode import decode_view
from scancell.analysis.phase import DecodeError
from scancell.analysis.projector_rig import CameraProjectorRig, read_rig
from scancell.analysis.projector_scan import reconstruct
from scancell.analysis.stereo_calibration import CalibrationError
from scancell.model.pattern_set import PatternSet, preset
from scancell.sim.projector_rig_sim import Plane, RigSimulator, board_pose, default_rig

from .conftest import SLSTUDIO_DATA

SCALE = 0.4  # 512 x 410 camera frames
SHEET = Plane(board_pose(450.0, (12.0, -18.0)))

SPECS = {
    "slstudio-2x3": preset("slstudio-2x3"),
    "slstudio-2x3-xy": preset("slstudio-2x3-xy"),
    "heterodyne-3x3": preset("heterodyne-3x3"),
    "gray-phase": preset("gray-phase"),
    "gray-phase-xy": preset("gray-phase-xy"),
    "plain gray + 4 steps": PatternSet.from_dict({"groups": [
        {"kind": "phase_shift", "axis": "x", "period_px": 32, "steps": 4},
        {"kind": "gray_code", "axis": "x", "bits": 6, "stripe_px": 32}]}),
    "inverse complementary gray, sign -1": PatternSet.from_dict({"groups": [
        {"kind": "complementary_gray_code", "axis": "x", "bits": 6, "inverse": True},
        {"kind": "phase_shift", "axis": "x", "periods": 32, "steps": 4, "sign": -1}]}),
    "3, 4 and 5 steps": PatternSet.from_dict({"groups": [
        {"kind": "phase_shift", "axis": "x", "periods": 1, "steps": 3},
        {"kind": "phase_shift", "axis": "x", "periods": 8, "steps": 4},
        {"kind": "phase_shift", "axis": "x", "periods": 48, "steps": 5}]}),
}


@pytest.mark.unit
@pytest.mark.parametrize("name", sorted(SPECS))
def test_every_pattern_kind_decodes_the_true_plane(name):
    spec = SPECS[name]
    sim = RigSimulator(default_rig(SCALE), seed=3)
    frames = sim.render(SHEET, spec)
    view = decode_view(frames, spec, sim.truth.projector_size)
    true_uv = sim.true_projector_coords(SHEET)
    assert view.valid_share > 0.9, view.rejected
    b = DecodeLimits().border_px  # the image's outer pixels are masked before triangulation
    for i, axis in enumerate(spec.axes):
        err = (view.coords[axis] - true_uv[..., i])[b:-b, b:-b]
        ok = np.isfinite(err)
        sigma = view.sigma[axis][b:-b, b:-b][ok]
        fringe = sim.truth.projector_size[i] / max(g.periods_across(sim.truth.projector_size[i])
                                                   for g in spec.phase_groups(axis))
        wrong_order = np.abs(err[ok]) > fringe / 2
        assert wrong_order.mean() < 1e-4, (axis, wrong_order.sum())
        # the decode's noise as it states it (the response's residual error on top)
        good = err[ok][~wrong_order]
        assert np.sqrt(np.mean(good ** 2)) < 3 * np.sqrt(np.mean(sigma ** 2)) + 0.05, axis
    cloud = reconstruct(sim.truth, view)
    n, d = SHEET.T_cam_from_board[:3, 2], SHEET.T_cam_from_board[:3, 2] @ SHEET.T_cam_from_board[:3, 3]
    r = cloud.points.astype(float) @ n - d
    assert abs(np.mean(r)) < 0.01  # mm: no bias
    assert np.sqrt(np.mean(r ** 2)) < 2 * np.sqrt(np.mean(cloud.uncertainty ** 2)) + 0.01
    assert np.percentile(np.abs(r), 99.9) < 1.0  # mm: no wrong fringe order left in the cloud


@pytest.mark.unit
@pytest.mark.parametrize("bits", [12, 16])
def test_12_and_16_bit_frames_decode_like_8_bit(bits):
    spec = preset("slstudio-2x3")
    views = {}
    for depth in (8, bits):
        sim = RigSimulator(default_rig(SCALE), seed=5, bit_depth=depth)
        frames = sim.render(SHEET, spec)
        assert frames[0].dtype == (np.uint8 if depth == 8 else np.uint16)
        views[depth] = decode_view(frames, spec, sim.truth.projector_size)
    a, b = views[8], views[bits]
    # the same scene on the 8-bit scale: the same noise (the finer quantisation aside) and valid area
    assert abs(a.valid_share - b.valid_share) < 0.01
    assert 0.7 < b.noise_dn / a.noise_dn < 1.1
    both = np.isfinite(a.coords["x"]) & np.isfinite(b.coords["x"])
    assert np.median(np.abs(a.coords["x"][both] - b.coords["x"][both])) < 0.2


@pytest.mark.unit
def test_bad_frames_are_named():
    spec = preset("slstudio-2x3")
    sim = RigSimulator(default_rig(SCALE), seed=1)
    frames = sim.render(SHEET, spec)
    names = [f"f{k}.png" for k in range(6)]
    mixed = [*frames[:5], frames[5].astype(np.uint16) * 16]
    with pytest.raises(DecodeError, match=r"f5.png: uint16 pixels, but f0.png is uint8"):
        decode_view(mixed, spec, sim.truth.projector_size, names=names)
    with pytest.raises(DecodeError, match="5 frames, but the pattern set slstudio-2x3 needs 6"):
        decode_view(frames[:5], spec, sim.truth.projector_size, names=names)
    small = [*frames[:3], frames[3][:-2], *frames[4:]]
    with pytest.raises(DecodeError, match=r"f3.png: size"):
        decode_view(small, spec, sim.truth.projector_size, names=names)


@pytest.mark.unit
def test_limits_can_be_overridden_and_follow_the_noise():
    spec = preset("slstudio-2x3")
    sim = RigSimulator(default_rig(SCALE), seed=2)
    frames = sim.render(SHEET, spec)
    derived = decode_view(frames, spec, sim.truth.projector_size)
    fixed = decode_view(frames, spec, sim.truth.projector_size,
                        DecodeLimits(min_modulation_dn=90.0, noise_dn=2.0))
    assert fixed.min_modulation_dn == 90.0 and fixed.noise_dn == 2.0
    assert fixed.valid_share < derived.valid_share
    # twice the noise: the modulation threshold doubles (z sigma of the order's noise)
    doubled = decode_view(frames, spec, sim.truth.projector_size,
                          DecodeLimits(noise_dn=2 * derived.noise_dn))
    assert doubled.min_modulation_dn == pytest.approx(2 * derived.min_modulation_dn, rel=1e-6)
    in_spec = PatternSet.from_dict({**spec.to_dict(), "limits": {"min_modulation_dn": 90.0}})
    assert decode_view(frames, in_spec, sim.truth.projector_size).min_modulation_dn == 90.0


@pytest.mark.unit
def test_response_compensation_only_where_the_histogram_supports_it():
    """The 1-period cue covers a fraction of one fringe: its folded histogram says nothing about
    the response; it borrows the 16-period group's estimate instead of raising an alarm."""
    spec = preset("slstudio-2x3")
    sim = RigSimulator(default_rig(SCALE), seed=4)
    view = decode_view(sim.render(SHEET, spec), spec, sim.truth.projector_size)
    r = view.response
    assert r["estimated_from"] == [0] and r["lent_to"] == [1]
    assert r["phase_error_pp_rad"]["1"] == r["phase_error_pp_rad"]["0"]


@pytest.mark.unit
def test_slstudio_calibration_is_read_as_it_is(tmp_path):
    xml = SLSTUDIO_DATA / "calibration" / "calibration.xml"
    if not xml.exists():
        pytest.skip(f"{SLSTUDIO_DATA} is not beside this checkout (or SCANCELL_SHARED_DATA)")
    rig = read_rig(xml)
    assert isinstance(rig, CameraProjectorRig)
    assert rig.image_size == (1688, 1352) and rig.projector_size == (1824, 1140)
    assert rig.K_cam[0, 0] == pytest.approx(2195.12036, rel=1e-6)
    assert rig.T == pytest.approx([-145.282562, -36.4983406, 67.9231644], rel=1e-6)
    # a camera-only file for a camera-projector rig
    text = xml.read_text()
    start, end = text.index("<Kp"), text.index("</Tp>") + len("</Tp>")
    broken = tmp_path / "camera_only.xml"
    broken.write_text(text[:start] + text[end:])
    with pytest.raises(CalibrationError, match=r"camera_only.xml: a camera-only calibration .*Kp"):
        read_rig(broken)


@pytest.mark.unit
def test_a_rig_file_round_trips_and_states_its_mode(tmp_path):
    rig = default_rig(SCALE)
    rig.write(tmp_path / "rig.yaml")
    again = read_rig(tmp_path / "rig.yaml")
    assert isinstance(again, CameraProjectorRig) and again.projector_size == rig.projector_size
    assert np.allclose(again.R, rig.R) and np.allclose(again.T, rig.T)
    text = (tmp_path / "rig.yaml").read_text()
    assert "mode: camera_projector" in text
    (tmp_path / "noproj.yaml").write_text(text.split("projector_width")[0])
    with pytest.raises(CalibrationError, match="mode camera_projector but no projector"):
        read_rig(tmp_path / "noproj.yaml")


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "scancell", *args], capture_output=True, text=True,
                          timeout=300)


@pytest.mark.process
def test_a_simulated_rig_is_calibrated_from_phase_maps_and_measures_the_true_plane(tmp_path):
    """scancell sim rig -> scancell calibrate projector-rig -> scancell decode, by the CLIs."""
    r = _run("sim", "rig", "--scale", "0.5", "--poses", "10", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    rig_file = tmp_path / "rig.yaml"
    r = _run("calibrate", "projector-rig", "--patterns", str(tmp_path / "patterns.json"),
             "--target", "9x7x18", "--out", str(rig_file),
             *sorted(str(p) for p in tmp_path.glob("board_*")))
    assert r.returncode == 0, r.stderr
    assert "calibration from 10 poses" in r.stdout
    got, true = read_rig(rig_file), read_rig(tmp_path / "rig_true.yaml")
    d_r = got.R @ true.R.T
    assert np.degrees(np.arccos(np.clip((np.trace(d_r) - 1) / 2, -1, 1))) < 0.05
    assert np.linalg.norm(got.T - true.T) < 0.3  # mm
    assert got.K_proj[0, 0] == pytest.approx(true.K_proj[0, 0], rel=1e-3)
    assert got.K_cam[0, 0] == pytest.approx(true.K_cam[0, 0], rel=1e-3)
    out = tmp_path / "plane.ply"
    r = _run("decode", "--calib", str(rig_file), "--patterns", str(tmp_path / "patterns.json"),
             "--images", str(tmp_path / "plane"), "--out", str(out))
    assert r.returncode == 0, r.stderr
    truth = json.loads((tmp_path / "truth.json").read_text())
    pts, fields = read_ply(out)
    res = pts @ np.array(truth["plane_normal"]) - truth["plane_offset_mm"]
    # mm, against the truth (measured: -0.020 / 0.032 mm at seeds 0 and 1; 8 poses: -0.09 / 0.10)
    assert abs(np.mean(res)) < 0.06 and np.sqrt(np.mean(res ** 2)) < 0.08
    assert "uncertainty" in fields
    header = out.read_bytes()[:600].decode("ascii", "replace")
    assert "comment frame: camera" in header


@pytest.mark.process
def test_decode_cli_refuses_bad_input_and_writes_nothing(tmp_path):
    sim = RigSimulator(default_rig(SCALE), seed=1)
    rig = tmp_path / "rig.yaml"
    sim.truth.write(rig)
    frames = sim.render(SHEET, preset("slstudio-2x3"))
    good = tmp_path / "good"
    good.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(good / f"frame_{k}.png"), f)
    out = tmp_path / "out.ply"

    def decode(images: Path, patterns: str = "slstudio-2x3", calib: Path = rig):
        return _run("decode", "--calib", str(calib), "--patterns", patterns, "--images",
                    str(images), "--out", str(out))

    r = decode(good, "heterodyne-3x3")  # the spec disagrees with the frames' count
    assert r.returncode == 2 and "6 frames" in r.stderr and "needs 9" in r.stderr
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(mixed / f"frame_{k}.png"), f if k else f.astype(np.uint16) * 257)
    r = decode(mixed)
    assert r.returncode == 2 and "frame_1.png: uint8 pixels, but" in r.stderr
    small = tmp_path / "small"
    small.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(small / f"frame_{k}.png"), f[:-4])
    r = decode(small)
    assert r.returncode == 2 and "frame_0.png: the frames are" in r.stderr
    spec = tmp_path / "short_gray.toml"
    spec.write_text('[[groups]]\nkind = "phase_shift"\naxis = "x"\nperiod_px = 40\nsteps = 3\n'
                    '[[groups]]\nkind = "gray_code"\naxis = "x"\nbits = 3\nstripe_px = 40\n')
    six = tmp_path / "six"
    six.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(six / f"frame_{k}.png"), f)
    r = decode(six, str(spec))
    assert r.returncode == 2 and "short_gray.toml" in r.stderr and "short of the projector" in r.stderr
    text = rig.read_text()
    noproj = tmp_path / "noproj.yaml"
    noproj.write_text(text.split("projector_width")[0])
    r = decode(good, calib=noproj)
    assert r.returncode == 2 and "noproj.yaml" in r.stderr and "no projector" in r.stderr
    assert not out.exists() and not list(tmp_path.glob(".out.ply*"))
    r = decode(good)
    assert r.returncode == 0, r.stderr
    assert out.exists()
    # a rig in a folder whose name is not ASCII: its path goes into the PLY header escaped
    other = tmp_path / "Prüfstand"
    other.mkdir()
    (other / "rig.yaml").write_text(rig.read_text())
    r = decode(good, calib=other / "rig.yaml")
    assert r.returncode == 0, r.stderr
    assert b"Pr\\xfcfstand" in out.read_bytes()[:600]


@pytest.mark.process
def test_decode_limits_from_the_cell_config_and_the_command_line(tmp_path):
    sim = RigSimulator(default_rig(SCALE), seed=1)
    rig = tmp_path / "rig.yaml"
    sim.truth.write(rig)
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    for k, f in enumerate(sim.render(SHEET, preset("slstudio-2x3"))):
        cv2.imwrite(str(frames_dir / f"f{k}.png"), f)
    cell = tmp_path / "cell.toml"
    cell.write_text("[cell]\nname = 'x'\n[scanner]\ndecode_limits = {min_modulation_dn = 40.0}\n")
    base = ["decode", "--calib", str(rig), "--patterns", "slstudio-2x3", "--images",
            str(frames_dir), "--out", str(tmp_path / "o.ply"), "--config", str(cell)]
    r = _run(*base)
    assert r.returncode == 0, r.stderr
    assert "modulation threshold 40.0 DN" in r.stdout
    r = _run(*base, "--limit", "min_modulation_dn=20")
    assert r.returncode == 0 and "modulation threshold 20.0 DN" in r.stdout
    r = _run(*base, "--limit", "min_modulation=20")
    assert r.returncode == 2 and "unknown limit(s) ['min_modulation']" in r.stderr
