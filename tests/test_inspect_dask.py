"""The inspection's deviation on a Dask cluster (issue 37, item 4: large-job inspection on the
reprocess's cluster): tiles computed on a local cluster of two worker processes equal the tiles
computed here, bit for bit, both workers taking tiles; ``scancell inspect --scheduler local``
writes the same deviation PLY as without it; an unreachable scheduler is named and nothing is
written; a worker that loads another file at the nominal's path refuses it by name."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scancell.analysis import deviation
from scancell.analysis.cloud_io import write_ply
from scancell.analysis.deviation import closest_points_moved
from scancell.cli import main as cli_main

from .conftest import free_port
from .test_inspect import cad, moved, sample  # noqa: F401  (cad: the module's fixture)

pytestmark = pytest.mark.timeout(300)


def arrays(result) -> dict[str, np.ndarray]:
    part, cp, near = result
    out = {"triangle": cp.triangle, "deviation": cp.deviation}
    for name, a in (("part", part), ("closest", cp.points), ("distance", cp.distance),
                    ("near", near)):
        if a is not None:
            out[name] = a
    return out


@pytest.mark.e2e
def test_tiles_on_two_workers_equal_the_tiles_here_bit_for_bit(cad, monkeypatch):  # noqa: F811
    from distributed import get_task_stream
    from scancell.batch.cluster import close, connect
    from scancell.batch.inspect import cluster_tiles

    monkeypatch.setattr(deviation, "CHUNK", 15_000)  # 7 tiles: more than the workers take at once
    truth = sample(("dent",), n=100_000)
    pts, T_measured_from_part = moved(truth, seed=4)
    T = np.linalg.inv(T_measured_from_part)
    nominal = cad["step_nominal"]
    client = connect(None, 2)
    try:
        runner = cluster_tiles(client)
        for dtype, within in ((np.float32, 5.0), (np.float64, None)):
            here = arrays(closest_points_moved(nominal, pts, T, dtype, within))
            with get_task_stream(client) as stream:
                there = arrays(closest_points_moved(nominal, pts, T, dtype, within, runner))
            assert len({t["worker"] for t in stream.data}) == 2
            assert len(stream.data) == 7
            assert here.keys() == there.keys()
            for name in here:
                assert here[name].dtype == there[name].dtype, name
                assert np.array_equal(here[name], there[name]), name
    finally:
        close(client)


@pytest.mark.e2e
def test_inspect_on_a_local_cluster_writes_what_inspect_here_writes(cad, tmp_path,  # noqa: F811
                                                                    monkeypatch):
    monkeypatch.setattr(deviation, "CHUNK", 20_000)
    measured, _ = moved(sample(("dent", "flange"), n=80_000), seed=3)
    write_ply(tmp_path / "measured.ply", measured)
    common = ["inspect", str(tmp_path / "measured.ply"), "--nominal", cad["step"], "--tolerance",
              "0.3"]
    assert cli_main([*common, "--out-ply", str(tmp_path / "here.ply"),
                     "--json", str(tmp_path / "here.json")]) == 1
    assert cli_main([*common, "--out-ply", str(tmp_path / "cluster.ply"), "--json",
                     str(tmp_path / "cluster.json"), "--scheduler", "local", "--workers",
                     "2"]) == 1
    assert (tmp_path / "here.ply").read_bytes() == (tmp_path / "cluster.ply").read_bytes()
    here, there = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("here", "cluster"))
    for key in ("deviation", "tolerances", "coverage", "alignment"):
        assert here[key] == there[key], key


@pytest.mark.process
def test_an_unreachable_scheduler_is_named_and_nothing_is_written(cad, tmp_path, capsys):  # noqa: F811
    write_ply(tmp_path / "measured.ply", sample((), n=20_000))
    address = f"tcp://127.0.0.1:{free_port()}"
    code = cli_main(["inspect", str(tmp_path / "measured.ply"), "--nominal", cad["stl"],
                     "--scheduler", address, "--json", str(tmp_path / "out.json"),
                     "--out-ply", str(tmp_path / "out.ply")])
    assert code == 3
    assert f"scheduler {address}: cannot be reached" in capsys.readouterr().err
    assert not (tmp_path / "out.json").exists() and not (tmp_path / "out.ply").exists()


@pytest.mark.unit
def test_a_worker_refuses_another_file_at_the_nominals_path(cad, tmp_path):  # noqa: F811
    from scancell.batch.inspect import ClusterInspectionError, cluster_tiles, deviation_tile

    nominal = cad["step_nominal"]
    pts = sample((), n=1_000)
    with pytest.raises(ClusterInspectionError, match="triangles on this worker"):
        deviation_tile(cad["step"], None, nominal.chordal_tolerance_mm,
                       len(nominal.triangles) + 1, pts, None, "float32", 5.0)
    # a nominal that is no file (made in memory) cannot be loaded by a worker: said before
    # anything is sent
    nominal.source, source = str(tmp_path / "gone.step"), nominal.source
    try:
        with pytest.raises(ClusterInspectionError, match="not a file the cluster's workers"):
            closest_points_moved(nominal, pts, None, np.float32, 5.0, cluster_tiles(object()))
    finally:
        nominal.source = source
