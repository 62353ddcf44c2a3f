"""``scancell fuse REC.mcap --scheduler``: a large job's fusion station by station on a Dask
cluster (scancell.batch.fuse) gives the model and the overlap figures, to the bit, of the fuse
worker's station-by-station path; what goes wrong is named. (Against a live job's recording:
tests/test_scan_part.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from scancell.cli import main as cli_main

from .conftest import free_port


def _stations(n: int = 4):
    """Overlapping strips of a gently curved surface, each in its own MCS, with its pose."""
    from scancell.workers.recorded_stations import RecordedStation
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(4)
    out, clouds = [], {}
    for k in range(n):
        g = np.arange(0.0, 80.0, 0.4)
        x, y = np.meshgrid(g + 50.0 * k, g)
        world = np.stack([x.ravel(), y.ravel(), 0.002 * (x.ravel() - 100) ** 2], axis=1)
        world += rng.normal(0, 0.01, world.shape) + np.array([1500.0, -800.0, 600.0])
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=k).as_matrix()
        T[:3, 3] = rng.uniform(-3000, 3000, 3)
        mcs = ((world - T[:3, 3]) @ T[:3, :3]).astype(np.float32)
        name = f"s{k + 1:02d}"
        out.append(RecordedStation(name, f"scan-{name}", f"scancell/t/scan/{name}/cloud", T))
        clouds[name] = mcs, np.full(len(mcs), 0.01 + 0.002 * k, np.float32)
    return out, clouds


@pytest.fixture
def in_process(monkeypatch):
    """A 2-worker cluster of threads in this process (the recording's reads patched in), and
    the stations it fuses."""
    from distributed import Client, LocalCluster
    from scancell.batch import fuse as batch_fuse

    poses, clouds = _stations()
    monkeypatch.setattr(batch_fuse, "station_cloud", lambda rec, st: clouds[st.name])
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                           dashboard_address=None)
    client = Client(cluster)
    try:
        yield client, poses, clouds
    finally:
        client.close()
        cluster.close()


@pytest.mark.process
def test_stations_fused_on_the_cluster_equal_the_fuse_workers_path(in_process, tmp_path):
    from scancell.analysis.station_store import StationStore, move_points
    from scancell.analysis.voxel_tiles import VoxelTiles
    from scancell.batch.fuse import fuse_recording
    from scancell.workers.fuse import overlap_comparer

    client, poses, clouds = in_process
    hand_eye = {"T_ecs_from_mcs": np.eye(4).tolist()}
    ticks = []
    got = fuse_recording(client, "rec.mcap", tmp_path / "spool", 1.0, ticks.append,
                         (poses, hand_eye))
    assert len(ticks) == 2 * len(poses) - 1  # a station's task each; overlaps from the 2nd on
    # the fuse worker's way: one station after the other, one store, one tile folder
    mcs = StationStore(tmp_path / "live" / "mcs")
    comparer = overlap_comparer(mcs, tmp_path / "live" / "world")
    tiles = VoxelTiles(tmp_path / "live" / "tiles", 1.0)
    for st in poses:
        pts, unc = clouds[st.name]
        mcs.put(st.name, pts, None, unc)
        world = move_points(pts, st.T_world_from_ecs)
        comparer.store.place(st.name, st.T_world_from_ecs)
        comparer.add(st.name, world, unc)
        tiles.add(world, unc)
    want = comparer.report().to_json()
    assert sum(p["n"] for p in want["pairs"]) > 10_000
    assert got.metrics.to_json() == want
    model = np.concatenate([rec["p"] for rec in got.fused.model.chunks()])
    sigma = np.concatenate([rec["sigma"] for rec in got.fused.model.chunks()])
    live_p, live_s = tiles.model()
    np.testing.assert_array_equal(model, live_p)
    np.testing.assert_array_equal(sigma, live_s.astype(sigma.dtype))  # as the model file keeps it
    assert got.stations == [st.name for st in poses]
    assert got.fused.merged_count == sum(len(c[0]) for c in clouds.values())


@pytest.mark.process
def test_a_station_that_fails_on_a_worker_is_named(in_process, tmp_path, monkeypatch):
    from scancell.analysis.fusion import FusionError
    from scancell.batch import fuse as batch_fuse

    client, poses, clouds = in_process

    def cloud(rec, st):
        if st.name == "s03":
            raise FusionError(f"{rec}: station s03: no cloud for scan scan-s03")
        return clouds[st.name]

    monkeypatch.setattr(batch_fuse, "station_cloud", cloud)
    with pytest.raises(batch_fuse.ClusterFusionError,
                       match=r"station s03 \(station\): FusionError: .*rec.mcap: station s03: no cloud"):
        batch_fuse.fuse_recording(client, "rec.mcap", tmp_path / "spool", 1.0,
                                  layout=(poses, {"T_ecs_from_mcs": np.eye(4).tolist()}))


@pytest.mark.process
def test_bad_recordings_and_an_unreachable_scheduler_are_named_and_nothing_is_left(
        tmp_path, capsys, monkeypatch):
    from scancell.workers import recorded_stations

    out = tmp_path / "fused.ply"
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap at all")
    for source, said in ((tmp_path / "missing.mcap", "missing.mcap: no such recording"),
                         (garbage, "garbage.mcap: not an MCAP file"),
                         (tmp_path / "cloud.ply", "--scheduler fuses a recording (.mcap)")):
        assert cli_main(["fuse", str(source), "--out", str(out), "--scheduler", "local"]) == 2
        assert said in capsys.readouterr().err
    # a recording of stations (its reading patched in) whose scheduler cannot be reached
    monkeypatch.setattr(recorded_stations, "recorded_poses",
                        lambda path: (_stations(2)[0], {"T_ecs_from_mcs": np.eye(4).tolist()}))
    address = f"tcp://127.0.0.1:{free_port()}"
    assert cli_main(["fuse", str(garbage), "--out", str(out), "--scheduler", address]) == 3
    assert f"scheduler {address}: cannot be reached" in capsys.readouterr().err
    assert not out.exists()
    assert not list(tmp_path.glob(".scancell-fuse-*")), "the spool is removed"
