"""``convert`` of many files and ``simulate`` of many stations on a cluster: the same bytes."""

from __future__ import annotations

import filecmp
from pathlib import Path

import pytest
from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.core.errors import DataFormatError
from semantic3d.datasets.simulator import simulate
from semantic3d.datasets.simulator.errors import SimulationConfigError
from semantic3d.scale.cluster import DaskCluster
from semantic3d.scale.convert import convert_files_on_cluster
from semantic3d.scale.simulate import simulate_on_cluster

runner = CliRunner()


def _same_files(one: Path, other: Path) -> list[str]:
    """The names of ``one``'s files, after checking ``other`` holds them with the same bytes."""
    names = sorted(path.name for path in one.iterdir())
    assert names == sorted(path.name for path in other.iterdir())
    _, mismatch, errors = filecmp.cmpfiles(one, other, names, shallow=False)
    assert (mismatch, errors) == ([], [])
    return names


def test_convert_many_files_identical(cluster: DaskCluster, scan_dir: Path, tmp_path: Path) -> None:
    sources = [scan_dir / f"{name}.txt" for name in ("test", "other")]
    seen: list[tuple[int, int]] = []
    for suffix in (".ply", ".las", ".xyz"):
        jobs = [(source, tmp_path / suffix / f"{source.stem}{suffix}") for source in sources]
        here = convert_files_on_cluster(jobs, cluster=None)
        cluster_jobs = [(source, tmp_path / f"c{suffix}" / out.name) for source, out in jobs]
        seen.clear()
        there = convert_files_on_cluster(
            cluster_jobs, cluster=cluster, progress=lambda done, total: seen.append((done, total))
        )
        assert [file.n_points for file in there] == [file.n_points for file in here]
        assert all(file.labelled for file in there) and seen[-1] == (2, 2)
        names = _same_files(tmp_path / suffix, tmp_path / f"c{suffix}")
        if suffix == ".xyz":
            assert names == ["other.labels", "other.xyz", "test.labels", "test.xyz"]


def test_convert_task_error_is_raised_as_itself(cluster: DaskCluster, tmp_path: Path) -> None:
    bad = tmp_path / "bad.las"
    bad.write_bytes(b"garbage" * 50)
    with pytest.raises(DataFormatError, match="expected a LAS/LAZ file"):
        convert_files_on_cluster([(bad, tmp_path / "out" / "bad.ply")], cluster=cluster)
    assert not (tmp_path / "out" / "bad.ply").exists()


def test_convert_command_on_a_running_scheduler(
    cluster: DaskCluster, scan_dir: Path, tmp_path: Path
) -> None:
    sources = [str(scan_dir / f"{name}.txt") for name in ("test", "other")]
    address = cluster.client.scheduler.address
    plain = runner.invoke(app, ["convert", *sources, "--out", str(tmp_path / "a"), "--to", "laz"])
    assert plain.exit_code == 0, plain.output
    remote = runner.invoke(
        app,
        ["convert", *sources, "--out", str(tmp_path / "b"), "--to", "laz", "--scheduler", address],
    )
    assert remote.exit_code == 0, remote.output
    assert f"Dask: {address}" in remote.output
    assert plain.stdout.replace("/a/", "/b/") == remote.stdout
    assert _same_files(tmp_path / "a", tmp_path / "b") == ["other.laz", "test.laz"]
    again = runner.invoke(
        app,
        ["convert", *sources, "--out", str(tmp_path / "b"), "--to", "laz", "--scheduler", address],
    )
    assert again.exit_code == 2 and "already exists" in again.stderr


def test_simulate_stations_identical(cluster: DaskCluster, tmp_path: Path) -> None:
    settings = {"n_points": 3000, "stations": 2, "seed": 4, "chunk_size": 1000}
    single = simulate("street", out=tmp_path / "single", **settings)
    seen: list[tuple[int, int]] = []
    distributed = simulate_on_cluster(
        "street",
        out=tmp_path / "cluster",
        cluster=cluster,
        progress=lambda done, total: seen.append((done, total)),
        **settings,
    )
    assert seen[-1] == (2, 2)
    assert distributed.n_points == single.n_points > 0
    assert [scan.class_counts for scan in distributed.scans] == [
        scan.class_counts for scan in single.scans
    ]
    assert _same_files(tmp_path / "single", tmp_path / "cluster") == [
        "street.json",
        "street_station1.labels",
        "street_station1.txt",
        "street_station2.labels",
        "street_station2.txt",
    ]


def test_simulate_on_cluster_rejects_bad_settings(tmp_path: Path) -> None:
    with pytest.raises(SimulationConfigError, match="unknown scene 'town'"):
        simulate_on_cluster("town", out=tmp_path, n_points=10, cluster=None)
    with pytest.raises(SimulationConfigError, match=r"stations: expected an integer in 1\.\.3"):
        simulate_on_cluster("street", out=tmp_path, n_points=10, stations=4, cluster=None)
    assert not any(tmp_path.iterdir())


def test_simulate_command_on_a_running_scheduler(cluster: DaskCluster, tmp_path: Path) -> None:
    args = ["simulate", "--scene", "square", "--stations", "2", "--points", "2000", "--seed", "1"]
    plain = runner.invoke(app, [*args, "--out", str(tmp_path / "a")])
    assert plain.exit_code == 0, plain.output
    address = cluster.client.scheduler.address
    remote = runner.invoke(app, [*args, "--out", str(tmp_path / "b"), "--scheduler", address])
    assert remote.exit_code == 0, remote.output
    assert f"Dask: {address}" in remote.output
    assert len(_same_files(tmp_path / "a", tmp_path / "b")) == 5
