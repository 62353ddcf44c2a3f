"""The paper's metric tool on synthetic clouds of known offset and tilt, and its CLI."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scancell.analysis.cloud_io import write_ply
from scancell.analysis.metrics import MetricsError, compare_clouds


def plane(spacing: float = 0.5, size: float = 60.0, offset: float = 0.0, tilt_deg: float = 0.0,
          shift_xy: float = 0.0, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    g = np.arange(-size / 2, size / 2, spacing) + shift_xy
    x, y = np.meshgrid(g, g)
    z = offset + y * np.tan(np.radians(tilt_deg))
    rng = np.random.default_rng(seed)
    return np.stack([x.ravel(), y.ravel(), z.ravel() + rng.normal(0, noise, x.size)], axis=1)


@pytest.mark.unit
def test_known_offset_gives_that_translation_and_no_rotation():
    a = plane()
    b = plane(offset=0.3, shift_xy=0.25)
    out = compare_clouds({"a": a, "b": b}).to_json()
    assert out["translation_mm"]["mean"] == pytest.approx(0.3, abs=1e-6)
    assert out["translation_mm"]["p_lt_0_6"] == 1.0
    assert out["rotation_deg"]["mean"] < 1e-3
    assert out["radius_mm"] == pytest.approx(6 * 0.5, rel=1e-6)


@pytest.mark.unit
def test_known_tilt_gives_that_rotation():
    a = plane()
    b = plane(tilt_deg=2.0, shift_xy=0.25)
    out = compare_clouds({"a": a, "b": b}).to_json()
    assert out["rotation_deg"]["mean"] == pytest.approx(2.0, abs=0.01)
    # the distance to the tilted plane grows with |y|: mean |y|·tan 2° over ±30 mm ≈ 0.52 mm
    assert out["translation_mm"]["mean"] == pytest.approx(15 * np.tan(np.radians(2)), rel=0.05)
    assert 0.3 < out["translation_mm"]["p_lt_0_6"] < 0.8


@pytest.mark.unit
def test_several_clouds_give_every_overlapping_pair():
    clouds = {"a": plane(), "b": plane(offset=0.1, shift_xy=0.2), "c": plane(offset=200.0)}
    out = compare_clouds(clouds).to_json()
    pairs = {(p["a"], p["b"]): p for p in out["pairs"]}
    assert pairs[("a", "b")]["n"] > 10000 and pairs[("a", "c")]["n"] == 0
    assert pairs[("a", "b")]["translation_mean_mm"] == pytest.approx(0.1, abs=1e-6)


@pytest.mark.unit
def test_no_overlap_nan_and_empty_are_clear_errors():
    with pytest.raises(MetricsError, match="no overlap"):
        compare_clouds({"a": plane(), "b": plane(offset=50.0)})
    bad = plane()
    bad[7] = np.nan
    with pytest.raises(MetricsError, match="b: 1 points are NaN"):
        compare_clouds({"a": plane(), "b": bad})
    with pytest.raises(MetricsError, match="empty"):
        compare_clouds({"a": plane(), "b": np.zeros((0, 3))})
    with pytest.raises(MetricsError, match="two clouds"):
        compare_clouds({"a": plane()})


@pytest.mark.process
def test_cli_json_plots_and_bad_input(tmp_path):
    write_ply(tmp_path / "a.ply", plane(noise=0.005))
    write_ply(tmp_path / "b.ply", plane(offset=0.2, shift_xy=0.25, noise=0.005, seed=1))
    write_ply(tmp_path / "far.ply", plane(offset=500.0))
    run = [sys.executable, "-m", "scancell", "metrics"]
    r = subprocess.run([*run, str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "--json",
                        str(tmp_path / "m.json"), "--plots", str(tmp_path / "plots")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads((tmp_path / "m.json").read_text())
    assert set(out["translation_mm"]) == {"max", "min", "mean", "std", "p_lt_0_6", "p_lt_1_0"}
    assert set(out["rotation_deg"]) == {"max", "min", "mean", "std", "p_lt_10"}
    assert out["pairs"][0]["a"] == "a.ply" and out["pairs"][0]["n"] > 0
    assert out["translation_mm"]["mean"] == pytest.approx(0.2, abs=0.02)
    assert (tmp_path / "plots" / "translation_error.png").stat().st_size > 1000
    assert (tmp_path / "plots" / "rotation_error.png").stat().st_size > 1000
    r = subprocess.run([*run, str(tmp_path / "a.ply"), str(tmp_path / "far.ply")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "no overlap" in r.stderr
    r = subprocess.run([*run, str(tmp_path / "a.ply"), str(tmp_path / "missing.ply")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "missing.ply" in r.stderr


@pytest.mark.unit
def test_grid_neighbourhoods_agree_with_a_kd_tree():
    """The grid kernels against scipy's k-d tree: the same nearest points, the same normals."""
    from scancell.analysis.grid_kernels import CellGrid
    from scancell.analysis.metrics import nearest_within, normals
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    xy = rng.uniform(-40, 40, (30000, 2))
    a = np.column_stack([xy, 3 * np.sin(xy[:, 0] / 9) + rng.normal(0, 0.01, len(xy))])
    b = a[:15000] + rng.normal(0, 0.3, (15000, 3))
    q = np.vstack([a, rng.uniform(-200, 200, (500, 3))])  # some far outside b
    r = 1.5
    grid = CellGrid(b, r)
    dist, idx = nearest_within(grid, q, r)
    d_ref, i_ref = cKDTree(b).query(q, distance_upper_bound=r)
    assert np.array_equal(np.isfinite(dist), np.isfinite(d_ref))
    ok = np.isfinite(d_ref)
    assert np.allclose(dist[ok], d_ref[ok]) and np.array_equal(idx[ok], i_ref[ok])
    assert np.all(idx[~ok] == -1)
    n = normals(a, r)
    d, i = cKDTree(a).query(a, k=80, distance_upper_bound=r)
    ref = np.empty_like(a)
    for k in range(0, len(a), 997):  # least-squares plane by SVD, point by point
        p = a[i[k][np.isfinite(d[k])]]
        ref[k] = np.linalg.svd(p - p.mean(axis=0))[2][2]
        assert abs(ref[k] @ n[k]) > 0.9999, k


@pytest.mark.unit
def test_clouds_compared_one_at_a_time_find_every_overlap_a_k_d_tree_finds():
    """The fuse worker compares each station as it comes; the box test that skips far-apart
    pairs and far points must lose no overlap point (checked against a k-d tree)."""
    from scancell.analysis.metrics import OverlapComparer
    from scipy.spatial import cKDTree

    clouds = {"a": plane(seed=1, noise=0.01), "b": plane(shift_xy=40.0, seed=2, noise=0.01),
              "far": plane(shift_xy=500.0, seed=3), "c": plane(shift_xy=-25.0, offset=0.05,
                                                                seed=4, noise=0.01)}
    comparer = OverlapComparer()
    for name, pts in clouds.items():
        comparer.add(name, pts, np.full(len(pts), 0.01))
    report = comparer.report()
    r = report.radius_mm
    assert [(p.a, p.b) for p in report.pairs] == [("a", "b"), ("a", "far"), ("a", "c"),
                                                  ("b", "far"), ("b", "c"), ("far", "c")]
    for p in report.pairs:
        d, _ = cKDTree(clouds[p.b]).query(clouds[p.a], distance_upper_bound=r)
        assert p.n == int(np.isfinite(d).sum()), (p.a, p.b)
    assert report.pairs[1].n == 0 and report.pairs[2].n > 0
    assert report.to_json()["translation_mm"]["weighted_mean"] > 0
    with pytest.raises(MetricsError, match="a: added twice"):
        comparer.add("a", clouds["a"])
    lone = OverlapComparer()
    lone.add("a", clouds["a"])
    with pytest.raises(MetricsError, match="at least two clouds"):
        lone.report()


@pytest.mark.unit
def test_streamed_statistics_are_those_of_the_values():
    from scancell.analysis.metrics import Distribution

    v = np.abs(np.random.default_rng(3).normal(0.0, 0.05, 200_000))
    d = Distribution(5.0, 5000, (0.06, 1.0))
    for part in np.array_split(v, 7):  # station by station
        d.add(part)
    assert d.n == len(v) and d.lo == v.min() and d.hi == v.max()
    assert d.mean == pytest.approx(v.mean(), rel=1e-12) and d.std == pytest.approx(v.std(), rel=1e-9)
    assert d.share_below(0.06) == np.mean(v < 0.06) and d.share_below(1.0) == 1.0
    assert abs(d.median() - np.median(v)) <= 0.5 * 5.0 / 5000 + 1e-12
    counts, edges = d.histogram(60)
    assert counts.sum() == len(v) and edges[0] == 0 and edges[-1] >= v.max()


def _pose(rng: np.random.Generator, far_mm: float) -> np.ndarray:
    """A rigid 4 x 4 with a random rotation and a translation ``far_mm`` away (a station's MCS
    seen from the tracker across a car body)."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-far_mm, far_mm, 3)
    return T


@pytest.mark.unit
@pytest.mark.parametrize("every", [1, 3])
def test_world_points_derived_from_the_mcs_store_are_the_bits_of_a_world_copy(tmp_path, every):
    """The fuse worker keeps a station's MCS cloud once and moves it into world when an
    overlap reads it back (WorldFromMcs): any box of its kept points has the same float32
    bits, order and 1-sigma as a second copy of those world points would."""
    from scancell.analysis.station_store import StationStore, WorldFromMcs, move_points

    rng = np.random.default_rng(11)
    mcs, copy = StationStore(tmp_path / "mcs"), StationStore(tmp_path / "copy")
    derived = WorldFromMcs(mcs, tmp_path / "world", every)
    for k in range(3):
        cloud = rng.uniform(-400, 400, (20_000 + 1_017 * k, 3)).astype(np.float32)
        unc = rng.uniform(0.01, 0.05, len(cloud)).astype(np.float32)
        nrm = rng.normal(size=cloud.shape).astype(np.float32)
        T = _pose(rng, 5000.0)
        world = move_points(cloud, T)
        # the same points moved one by one: no batch-size dependence in the rounding
        assert np.array_equal(np.concatenate([move_points(cloud[i:i + 1], T)
                                              for i in range(0, 50)]), world[:50])
        mcs.put(f"s{k}", cloud, None, unc)
        kept = slice(None, None, every)
        copy.put(f"s{k}", world[kept], nrm[kept], unc[kept])
        derived.place(f"s{k}", T)
        derived.put(f"s{k}", world[kept], nrm[kept], unc[kept])
        full, full_unc = derived.full(f"s{k}")
        assert np.array_equal(full, world) and np.array_equal(full_unc, unc)
        for lo, hi in ((None, None), *((c - 150.0 * f, c + 150.0 * f) for c, f in
                                       ((world[rng.integers(len(world))], 1.0),
                                        (world.mean(axis=0), 0.4), (world.max(axis=0), 1.0)))):
            want, got = copy.load(f"s{k}", lo, hi), derived.load(f"s{k}", lo, hi)
            for a, b in zip(want, got, strict=True):
                assert a.dtype == b.dtype and np.array_equal(a, b)
    assert sorted(p.name.split(".", 1)[1] for p in (tmp_path / "world").iterdir()) == [
        "normals.npy"] * 3
    with pytest.raises(ValueError, match="s9: no pose"):
        derived.put("s9", world, nrm, unc)
    with pytest.raises(ValueError, match="s0: 5 world points"):
        derived.put("s0", world[:5], nrm[:5], unc[:5])


@pytest.mark.unit
@pytest.mark.parametrize("every", [1, 4])
def test_overlap_figures_from_derived_world_points_equal_a_world_copys(tmp_path, every):
    """OverlapComparer on WorldFromMcs gives the report, to the bit, of one on a store of
    world points, whether it keeps every point or every 4th (the fuse worker's)."""
    from scancell.analysis.metrics import OverlapComparer
    from scancell.analysis.station_store import StationStore, WorldFromMcs, move_points

    rng = np.random.default_rng(7)
    mcs = StationStore(tmp_path / "mcs")
    copy = OverlapComparer(store=StationStore(tmp_path / "copy"), every=every)
    derived = OverlapComparer(store=WorldFromMcs(mcs, tmp_path / "world", every), every=every)
    with pytest.raises(ValueError, match="the store's own"):
        OverlapComparer(store=WorldFromMcs(mcs, tmp_path / "world", every), every=every + 1)
    for k, (o, x) in enumerate(((0.0, 0.0), (0.02, 20.0), (0.01, 40.0))):
        world_true = plane(offset=o, shift_xy=x, seed=k, noise=0.01) + np.array([2500.0, -1200.0, 800.0])
        T = _pose(rng, 3000.0)
        cloud = (world_true - T[:3, 3]) @ T[:3, :3]  # its MCS: T moves it back into world
        cloud = cloud.astype(np.float32)
        unc = np.full(len(cloud), 0.01, np.float32)
        mcs.put(f"s{k}", cloud, None, unc)
        world = move_points(cloud, T)
        derived.store.place(f"s{k}", T)
        copy.add(f"s{k}", world, unc)
        derived.add(f"s{k}", world, unc)
    a, b = copy.report().to_json(), derived.report().to_json()
    assert sum(p["n"] for p in a["pairs"]) > 1000
    assert a == b


@pytest.mark.unit
def test_normals_worked_out_on_demand_are_the_bits_of_every_points():
    from scancell.analysis.grid_kernels import CellGrid
    from scancell.analysis.metrics import NormalsOnDemand, mean_spacing, normals

    pts = plane(seed=3, noise=0.01).astype(np.float32)
    r = 6 * mean_spacing(pts)
    grid = CellGrid(pts, r)
    want = normals(pts, r, grid)
    lazy = NormalsOnDemand(pts, grid, r)
    idx = np.random.default_rng(1).integers(0, len(pts), 5000)
    assert np.array_equal(lazy[idx], want[idx])
    assert lazy.done.sum() == len(np.unique(idx))  # the rest not worked out
    assert np.array_equal(lazy[np.arange(len(pts))], want)


@pytest.mark.unit
def test_every_4th_point_as_c1_gives_the_figures_of_every_point():
    """The fuse worker's metric takes every 4th point of a station as C1 (its nearest points
    still among all of the later station's): a sample of the same overlaps, so the same
    figures within their sampling error, about a quarter of the points."""
    from scancell.analysis.metrics import OverlapComparer

    rng = np.random.default_rng(9)
    clouds = {n: plane(offset=o + rng.normal(0, 0.005), shift_xy=x, seed=k, noise=0.01)
              for k, (n, o, x) in enumerate((("a", 0.0, 0.0), ("b", 0.02, 20.0),
                                             ("c", 0.01, 40.0)))}
    every, all_ = OverlapComparer(every=4), OverlapComparer()
    for n, c in clouds.items():
        every.add(n, c, np.full(len(c), 0.01))
        all_.add(n, c, np.full(len(c), 0.01))
    a, b = all_.report().to_json(), every.report().to_json()
    for pa, pb in zip(a["pairs"], b["pairs"], strict=True):
        assert pb["n"] == pytest.approx(pa["n"] / 4, rel=0.05)  # the grid edges: not exact
    for key in ("mean", "std", "weighted_mean"):
        assert b["translation_mm"][key] == pytest.approx(a["translation_mm"][key], rel=0.03), key
    assert b["rotation_deg"]["mean"] == pytest.approx(a["rotation_deg"]["mean"], rel=0.03)


@pytest.mark.unit
def test_clouds_kept_on_disk_give_the_figures_of_clouds_kept_in_memory(tmp_path):
    """A fuse worker keeps its stations on disk (float32 points, float16 normals): the pairs
    and the figures are those of the stations kept in memory."""
    from scancell.analysis.metrics import OverlapComparer
    from scancell.analysis.station_store import StationStore

    rng = np.random.default_rng(5)
    clouds = {n: plane(offset=o + rng.normal(0, 0.005), shift_xy=x, seed=k, noise=0.01)
              for k, (n, o, x) in enumerate((("a", 0.0, 0.0), ("b", 0.02, 20.0),
                                             ("c", 0.01, 40.0)))}
    sig = {n: np.full(len(c), 0.01) for n, c in clouds.items()}
    mem, disk = OverlapComparer(), OverlapComparer(store=StationStore(tmp_path / "st"))
    for n, c in clouds.items():
        mem.add(n, c, sig[n])
        disk.add(n, c, sig[n])
    a, b = mem.report().to_json(), disk.report().to_json()
    assert [p["n"] for p in a["pairs"]] == [p["n"] for p in b["pairs"]]
    for key in ("mean", "std", "max", "p_lt_0_6", "weighted_mean", "normalised_median"):
        assert a["translation_mm"][key] == pytest.approx(b["translation_mm"][key], rel=1e-3,
                                                         abs=1e-5), key
    assert a["rotation_deg"]["mean"] == pytest.approx(b["rotation_deg"]["mean"], abs=0.01)
    assert sorted(p.name for p in (tmp_path / "st").iterdir())[:3] == [
        "00000.normals.npy", "00000.points.npy", "00000.uncertainty.npy"]


def test_the_overlap_figures_do_not_depend_on_the_order_the_pairs_come_in():
    """Live, pairs are measured as stations arrive; a reprocess may meet them in another order:
    the sums are exact (math.fsum of each pair's), so the figures are the same to the bit."""
    from scancell.analysis.metrics import TRANSLATION_BINS, Distribution

    rng = np.random.default_rng(3)
    chunks = [np.abs(rng.normal(0.0, 0.05, rng.integers(1, 5000))) * 10.0 ** rng.uniform(-3, 1)
              for _ in range(40)]
    forward, backward = Distribution(*TRANSLATION_BINS), Distribution(*TRANSLATION_BINS)
    for c in chunks:
        forward.add(c)
    for c in chunks[::-1]:
        backward.add(c)
    assert (forward.mean, forward.std, forward.n) == (backward.mean, backward.std, backward.n)


def test_rows_read_chunk_by_chunk_are_those_of_the_whole_array(tmp_path):
    """A station's subset is read a chunk at a time (not mapped whole): any ascending indices,
    across chunk edges, give the rows numpy gives; a file cut short or an index past the end is a
    clear error naming the file."""
    from scancell.analysis.station_store import npy_chunks, read_rows

    rng = np.random.default_rng(3)
    pts = rng.normal(size=(1000, 3)).astype(np.float32)
    sigma = rng.random(1000).astype(np.float32)
    np.save(tmp_path / "p.npy", pts)
    np.save(tmp_path / "s.npy", sigma)
    for idx in (np.sort(rng.choice(1000, 137, replace=False)), np.arange(63, 65),
                np.array([0, 999]), np.empty(0, np.int64)):
        np.testing.assert_array_equal(read_rows(tmp_path / "p.npy", idx, chunk=64), pts[idx])
        np.testing.assert_array_equal(read_rows(tmp_path / "s.npy", idx, chunk=64), sigma[idx])
    np.testing.assert_array_equal(read_rows(tmp_path / "p.npy", slice(None)), pts)
    assert [first for first, _ in npy_chunks(tmp_path / "p.npy", 400)] == [0, 400, 800]
    with pytest.raises(IndexError, match=r"p\.npy: rows 5\.\.1000 asked of 1000"):
        read_rows(tmp_path / "p.npy", np.array([5, 1000]))
    data = (tmp_path / "p.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[:-120])
    with pytest.raises(ValueError, match=r"cut\.npy: ends within rows 960"):
        read_rows(tmp_path / "cut.npy", np.array([1, 990]), chunk=64)


@pytest.mark.unit
def test_local_plane_distance_sees_a_sparse_reference_as_its_surface():
    """Stripe edges 2 mm apart on a plane z = 0: a point 0.3 mm above the plane between two
    stripes is 0.3 mm from the surface (1 mm from the nearest edge point); a point with no
    reference within reach is unsupported."""
    from scancell.analysis.metrics import local_plane_distance

    xs, ys = np.meshgrid(np.arange(0.0, 20.0, 2.0), np.arange(0.0, 20.0, 0.2))
    ref = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    pts = np.array([[9.0, 10.0, 0.3], [9.0, 10.0, -1.5], [60.0, 0.0, 0.0]])
    dist, supported = local_plane_distance(pts, ref, reach_mm=3.0)
    assert supported.tolist() == [True, True, False]
    assert dist[:2] == pytest.approx([0.3, 1.5], abs=1e-9) and np.isnan(dist[2])
