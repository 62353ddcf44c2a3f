"""Fusion into the tracker frame: true transforms give zero error against the part, an
estimated hand-eye the expected error; the fuse CLI and its bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scancell.analysis.cloud_io import read_ply, write_ply
from scancell.analysis.fusion import FusionError, Station, check_rigid, fuse
from scancell.analysis.metrics import compare_clouds
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.mechanics import mechanics_profile


@pytest.fixture(scope="module")
def stations():
    # the fusion's arithmetic: only the robot's joint noise (no compliance, vibration, drift)
    cell = SimCell(SimCellConfig(camera_scale=8, mechanics=mechanics_profile("ideal")))
    centre = cell.cfg.T_world_from_part[:3, 3]
    out = []
    for name, dy in (("s1", -120.0), ("s2", 80.0)):
        q = cell.ik_for_mcs(cell.mcs_pose_looking_at(centre + np.array([-250.0, dy, 0.0]), 620.0))
        cell.move_joints(q)
        out.append(Station(name, cell.true_points("left"), cell.true_T_world_from_ecs(cell.q)))
    # with the actual (noisy) pose the ECS and MCS are what the tracker and scanner would see
    return cell, out


@pytest.mark.unit
def test_true_transforms_put_every_point_on_the_part(stations):
    cell, st = stations
    T_true = cell.true_T_ecs_from_mcs()
    fused = fuse(st, T_true, voxel_mm=0.0)
    for name, pts in fused.per_station.items():
        assert np.abs(cell.surface_distance(pts)).max() < 0.02, name  # joint noise only
    out = compare_clouds(fused.per_station).to_json()
    assert out["pairs"][0]["n"] > 100 and out["translation_mm"]["mean"] < 0.02


@pytest.mark.unit
def test_a_wrong_hand_eye_shows_as_the_expected_error(stations):
    cell, st = stations
    T = cell.true_T_ecs_from_mcs().copy()
    T[:3, 3] += T[:3, :3] @ [0.0, 0.0, 0.3]  # the scanner 0.3 mm off along its view
    fused = fuse(st, T, voxel_mm=0.0)
    d = np.concatenate([cell.surface_distance(p) for p in fused.per_station.values()])
    assert 0.2 < d.mean() < 0.3  # seen along each surface normal, which the view nearly follows


@pytest.mark.unit
def test_resampling_thins_and_transforms_are_checked(stations):
    cell, st = stations
    fused = fuse(st, cell.true_T_ecs_from_mcs(), voxel_mm=2.0)
    assert len(fused.points) < 0.8 * fused.merged_count
    with pytest.raises(FusionError, match="proper rotation"):
        check_rigid(np.diag([1000.0, 1000.0, 1000.0, 1.0]), "T")


@pytest.mark.process
def test_fuse_cli_folder_and_bad_input(stations, tmp_path):
    cell, st = stations
    for s in st:
        write_ply(tmp_path / f"{s.name}.ply", s.points_mcs)
        (tmp_path / f"{s.name}.json").write_text(json.dumps(
            {"T_world_from_ecs": s.T_world_from_ecs.tolist()}))
    (tmp_path / "hand_eye.json").write_text(json.dumps(
        {"T_ecs_from_mcs": cell.true_T_ecs_from_mcs().tolist()}))
    run = [sys.executable, "-m", "scancell", "fuse"]
    r = subprocess.run([*run, str(tmp_path), "--out", str(tmp_path / "out" / "fused.ply")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "out" in r.stderr  # the output folder does not exist
    (tmp_path / "out").mkdir()
    r = subprocess.run([*run, str(tmp_path), "--out", str(tmp_path / "out" / "fused.ply"),
                        "--e57", str(tmp_path / "out" / "fused.e57"), "--mesh",
                        str(tmp_path / "out" / "mesh.ply"), "--report", str(tmp_path / "rep"),
                        "--refine"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "ICP refinement" in r.stdout and (tmp_path / "out" / "fused_icp.ply").exists()
    pts, _ = read_ply(tmp_path / "out" / "fused.ply")
    assert np.percentile(cell.surface_distance(pts), 99) < 0.05
    import open3d as o3d
    import pye57

    e57 = pye57.E57(str(tmp_path / "out" / "fused.e57"))
    raw = e57.read_scan_raw(0)
    assert e57.scan_count == 1 and len(raw["cartesianX"]) == len(pts)
    assert np.allclose(raw["cartesianX"] * 1000.0, pts[:, 0], atol=1e-3)  # E57 is in metres
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "out" / "mesh.ply"))
    assert len(mesh.triangles) > 1000
    assert np.median(cell.surface_distance(np.asarray(mesh.vertices))) < 0.5
    # the surface faces the cameras that saw it (normals turned towards each point's station)
    mesh.compute_vertex_normals()
    v, n = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    cams = np.array([(s.T_world_from_ecs @ cell.true_T_ecs_from_mcs())[:3, 3] for s in st])
    nearest = cams[np.argmin(np.linalg.norm(v[:, None] - cams[None], axis=2), axis=1)]
    assert np.mean(np.einsum("ij,ij->i", n, nearest - v) > 0) > 0.98
    report = (tmp_path / "rep" / "report.md").read_text()
    assert "Table 2" in report and "| s1 |" in report and "translation_error.png" in report
    assert "Multi-view ICP refinement (an extra" in report
    assert (tmp_path / "rep" / "translation_error.png").exists()
    (tmp_path / "s2.json").unlink()
    r = subprocess.run([*run, str(tmp_path), "--out", str(tmp_path / "x.ply")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "s2.json" in r.stderr
    r = subprocess.run([*run, str(tmp_path / "rec.mcap"), "--out", str(tmp_path / "x.ply")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "recording" in r.stderr


@pytest.mark.unit
def test_multi_view_icp_undoes_a_station_error_and_reports_it_apart(stations):
    """One station 0.4 mm off (a bad tracker shot): ICP held to the tracker prior pulls it back
    toward the part; the correction is reported, the tracker result stays as it was."""
    from scancell.analysis.refine import refine

    cell, st = stations
    fused = fuse(st, cell.true_T_ecs_from_mcs(), voxel_mm=0.0)
    moved = dict(fused.per_station)
    moved["s2"] = moved["s2"] + np.array([0.0, 0.0, 0.4])
    before = compare_clouds(moved).to_json()["translation_mm"]["mean"]
    r = refine(moved, voxel_mm=1.0, prior_weight=1e-3)
    after = compare_clouds(r.per_station).to_json()["translation_mm"]["mean"]
    assert after < 0.5 * before, (before, after)
    assert r.pairs == 1 and 0.1 < r.translation_mm["s2"] + r.translation_mm["s1"] < 0.6
    assert np.array_equal(moved["s2"], fused.per_station["s2"] + [0.0, 0.0, 0.4])  # untouched
    # a strong prior keeps the tracker poses
    held = refine(moved, voxel_mm=1.0, prior_weight=1e3)
    assert max(held.translation_mm.values()) < 0.05
    with pytest.raises(FusionError, match="at least two"):
        refine({"a": moved["s1"]})


@pytest.mark.unit
def test_error_budget_follows_the_tracker_noise(stations):
    """The ECS share scales with the tracker's sigma and is zero without noise; the budget
    names what dominates."""
    from scancell.analysis.error_budget import budget, ecs_noise_effect
    from scancell.analysis.station_pose import StationPose

    cell, st = stations
    q = cell.q_commanded
    pts = np.array([cell.smr_center_world(cell.j6_turned(q, a))
                    for a in (0.0, *cell.cfg.j6_angles_deg)])
    frame = [0.0, *cell.cfg.j6_angles_deg]
    T = cell.true_T_ecs_from_mcs()
    cloud = st[-1].points_mcs
    def pose(sigma: float) -> StationPose:
        return StationPose("j6", pts, np.full(pts.shape, sigma), T, tuple(frame), tuple(frame))

    assert ecs_noise_effect(pose(0.0), cloud) < 1e-9
    one = ecs_noise_effect(pose(0.005), cloud)
    two = ecs_noise_effect(pose(0.010), cloud)
    assert 0.0005 < one < 0.05 and two == pytest.approx(2 * one, rel=0.15)
    b = budget({"s1": one, "s2": one}, overlap_mean_mm=10 * one, true_mean_mm=0.02,
               hand_eye_rms_mm=0.008)
    assert b["dominant"].startswith("the rest")
    assert budget({"s1": one}, overlap_mean_mm=one, true_mean_mm=None,
                  hand_eye_rms_mm=None)["dominant"].startswith("the tracker")


def test_voxel_tiles_on_disk_give_the_weighted_means_of_the_whole_job(tmp_path):
    """The fuse worker adds each station's voxel sums to tiles on disk as it comes: the model
    read back tile by tile gives each voxel the inverse-variance weighted mean of all its points
    (as a plain per-voxel loop over the merged points does), across tile borders and negative
    coordinates; a point without a usable sigma weighs as its station's median one."""
    from scancell.analysis.voxel_tiles import VoxelTiles

    rng = np.random.default_rng(6)
    clouds = [rng.uniform([-9, -3, -2], [7, 6, 3], (n, 3)) for n in (3000, 0, 2000, 2500)]
    sigmas = [rng.uniform(0.01, 0.05, len(c)) for c in clouds]
    sigmas[2][:5] = np.nan
    tiles = VoxelTiles(tmp_path / "t", 0.5, tile_voxels=4)  # 2 mm tiles: many borders
    for c, s in zip(clouds, sigmas, strict=True):
        tiles.add(c, s)
    pts, sig = tiles.model()
    assert len(list((tmp_path / "t").glob("*.bin"))) > 20
    voxels: dict = {}
    for c, s in zip(clouds, sigmas, strict=True):
        w = np.where(np.isfinite(s), 1 / s ** 2, 1 / np.nanmedian(s) ** 2) if len(s) else s
        for k, p, wi in zip(map(tuple, np.floor(c / 0.5).astype(int)), c, w, strict=True):
            voxels.setdefault(k, []).append((p, wi))
    want = np.array([sum(wi * p for p, wi in v) / sum(wi for _, wi in v) for v in voxels.values()])
    want_s = np.array([1 / np.sqrt(sum(wi for _, wi in v)) for v in voxels.values()])
    assert len(pts) == len(want)
    a, b = np.lexsort(pts.T), np.lexsort(want.T)
    np.testing.assert_allclose(pts[a], want[b], rtol=0, atol=1e-9)
    np.testing.assert_allclose(sig[a], want_s[b], rtol=1e-9)
    tiles.remove()
    assert not (tmp_path / "t").exists()
    empty = VoxelTiles(tmp_path / "e", 1.0)
    empty.add(np.zeros((0, 3)))
    assert empty.model()[0].shape == (0, 3)


@pytest.mark.unit
def test_the_model_file_streams_its_chunks_into_ply_e57_and_the_true_error_figures(
        tmp_path, monkeypatch):
    """The fuse worker's model on disk, read chunk by chunk, gives the same PLY as the whole
    array written at once, an E57 any reader reads back, the true-error figures numpy gives
    over every point, and an even sample; a count that does not match leaves no file."""
    import pye57
    from scancell.analysis import model_file
    from scancell.analysis.cloud_io import CloudFileError, write_ply_chunks
    from scancell.analysis.export import ExportError, write_e57_chunks
    from scancell.analysis.model_file import ModelFile, ModelFileError
    from scancell.analysis.report import TrueErrorMap

    monkeypatch.setattr(model_file, "CHUNK", 700)  # many chunks, the last one short
    rng = np.random.default_rng(3)
    parts = [(rng.uniform(-800, 4200, (n, 3)), rng.uniform(0.01, 0.03, n)) for n in (1500, 1, 999)]
    pts, sig = np.concatenate([p for p, _ in parts]), np.concatenate([s for _, s in parts])
    model = ModelFile.write(tmp_path / "m.bin", parts)
    assert model.count == 2500 and model.weighted and not model.has_truth
    np.testing.assert_array_equal(model.lo, pts.min(axis=0))
    model.add_truth(lambda p: p[:, 2] / 1000.0 - 1.0)
    truth = np.abs(pts[:, 2] / 1000.0 - 1.0)
    rec = np.concatenate(list(model.chunks()))
    np.testing.assert_array_equal(rec["p"], pts)
    np.testing.assert_allclose(rec["true_error"], truth, rtol=1e-6)
    np.testing.assert_array_equal(model.sample(100), pts[::25])

    write_ply(tmp_path / "whole.ply", pts, {"uncertainty": sig, "true_error_mm": truth})
    write_ply_chunks(tmp_path / "chunks.ply", model.count, ["uncertainty", "true_error_mm"],
                     ((r["p"], {"uncertainty": r["sigma"], "true_error_mm": r["true_error"]})
                      for r in model.chunks()))
    assert (tmp_path / "whole.ply").read_bytes() == (tmp_path / "chunks.ply").read_bytes()
    with pytest.raises(CloudFileError, match="2500 points came for the 2600 announced"):
        write_ply_chunks(tmp_path / "short.ply", 2600, [], ((r["p"], {}) for r in model.chunks()))
    write_e57_chunks(tmp_path / "m.e57", model.count, model.lo, model.hi,
                     (r["p"] for r in model.chunks()))
    back = pye57.E57(str(tmp_path / "m.e57")).read_scan_raw(0)
    np.testing.assert_allclose(np.column_stack([back[f"cartesian{a}"] for a in "XYZ"]) * 1000,
                               pts, atol=1e-3)
    with pytest.raises(ExportError, match="2500 points came for the 9 announced"):
        write_e57_chunks(tmp_path / "short.e57", 9, model.lo, model.hi,
                         (r["p"] for r in model.chunks()))
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "chunks.ply", "m.bin", "m.e57", "whole.ply"]

    summed = TrueErrorMap(model.lo, model.hi)
    for r in model.chunks():
        summed.add(r["p"], r["true_error"])
    f = summed.figures()
    assert f["mean"] == pytest.approx(truth.mean(), abs=1e-6)
    assert f["std"] == pytest.approx(truth.std(), abs=1e-6)
    assert f["max"] == pytest.approx(truth.max(), abs=1e-6)
    assert abs(f["p95"] - np.percentile(truth, 95)) <= 0.5e-3 + 1e-6  # 1 µm bins
    whole = TrueErrorMap(pts.min(axis=0), pts.max(axis=0))
    whole.add(pts, truth)
    np.testing.assert_allclose(summed.rasters[0].image, whole.rasters[0].image, rtol=1e-6)
    assert summed.save(tmp_path / "map.png").stat().st_size > 10_000
    model.remove()
    with pytest.raises(ModelFileError, match="no points"):
        ModelFile.write(tmp_path / "empty.bin", [(np.zeros((0, 3)), None)])
    assert not (tmp_path / "empty.bin").exists()


@pytest.mark.unit
def test_the_final_model_is_put_together_from_its_parts():
    from scancell.workers.model_parts import ModelParts, ModelPartsError

    parts = ModelParts()
    a, b, c = (np.full((n, 3), float(n)) for n in (3, 2, 1))
    meta = {"job_id": "j", "final": True, "parts": 3}
    assert parts.add({**meta, "part": 2}, c) is None
    assert parts.add({**meta, "part": 0}, a) is None
    assert parts.waiting() == {"j": (2, 3)}
    np.testing.assert_array_equal(parts.add({**meta, "part": 1}, b), np.concatenate([a, b, c]))
    assert parts.waiting() == {}
    # a recording from before the parts: one message is the whole model
    np.testing.assert_array_equal(parts.add({"job_id": "old", "final": True}, a), a)
    with pytest.raises(ModelPartsError, match="job j: part 3 of 3"):
        parts.add({**meta, "part": 3}, a)
    # the parts as the fuse worker publishes them (meta names the model's size): each copied
    # into the model at its place, in any order; parts that do not fit are named
    model = np.arange(30, dtype=np.float32).reshape(10, 3)
    sized = {"job_id": "k", "final": True, "parts": 3, "points": 10}
    assert parts.add({**sized, "part": 2}, model[8:]) is None
    assert parts.add({**sized, "part": 0}, model[:4]) is None
    whole = parts.add({**sized, "part": 1}, model[4:8])
    np.testing.assert_array_equal(whole, model)
    assert whole.dtype == np.float32
    assert parts.add({**sized, "part": 0}, model[:4]) is None
    with pytest.raises(ModelPartsError, match="job k: part 1 has 3 points, the parts before it 4"):
        parts.add({**sized, "part": 1}, model[4:7])
    with pytest.raises(ModelPartsError, match="does not fit a model of 10"):
        parts.add({**sized, "part": 1}, model[:6])
    assert parts.add({**sized, "part": 2}, model[:1]) is None
    assert parts.add({**sized, "part": 0}, model[:4]) is None
    with pytest.raises(ModelPartsError, match="do not tile a model of 10 points"):
        parts.add({**sized, "part": 1}, model[4:8])
    assert parts.waiting() == {}
