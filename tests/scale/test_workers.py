"""A real ``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1 (the venv's
``dask`` command): a worker SIGKILLed mid-job (with its nanny, so it does not come back),
and workers whose memory limit is lower than the scans they work on."""

from __future__ import annotations

import contextlib
import filecmp
import os
import platform
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
import pytest

from semantic3d.baselines.common.prediction import predict_scan
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.scale.cluster import ClusterSpec, DaskCluster, connect
from semantic3d.scale.evaluation import compute_label_agreement_on_cluster
from semantic3d.scale.predict import ClusterPredictor

pytestmark = pytest.mark.slow

DASK = Path(sys.executable).with_name("dask")
MEMORY_LIMIT = 1 << 30
"""Each worker's memory limit at start; its nanny restarts it above 95 %."""

# Functions of this module run on the workers, which cannot import the tests package.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture(scope="module")
def real_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaskCluster]:
    """``dask scheduler`` + 2 ``dask worker`` (1 thread, nanny, memory limit) on 127.0.0.1."""
    if not DASK.is_file():
        pytest.skip("the dask command is not installed")
    logs = tmp_path_factory.mktemp("dask-logs")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    common = ["--no-dashboard"]
    commands = [
        [str(DASK), "scheduler", "--host", "127.0.0.1", "--port", str(port), *common],
        *(
            [
                str(DASK),
                "worker",
                address,
                "--host",
                "127.0.0.1",
                "--nthreads",
                "1",
                "--memory-limit",
                str(MEMORY_LIMIT),
                *common,
            ]
            for _ in range(2)
        ),
    ]
    processes: list[subprocess.Popen[bytes]] = []
    try:
        for number, command in enumerate(commands):
            log = (logs / f"{number}.log").open("wb")
            processes.append(
                subprocess.Popen(
                    command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
                )
            )
        with connect(ClusterSpec(scheduler=address, timeout_s=60)) as cluster:
            cluster.client.wait_for_workers(2, timeout=90)
            yield cluster
    finally:
        for process in processes:  # each in its own session: the nanny and its worker
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=10)


def _write_pair(folder: Path, n_points: int) -> list[Path]:
    """Two overlapping labelled scans of a 30 m square (B is A's points moved by 2 cm)."""
    from semantic3d.core.pointcloud import PointCloud
    from semantic3d.io.ascii import write_ascii_points

    rng = np.random.default_rng(5)
    xyz = rng.uniform(0.0, 30.0, (n_points, 3)) * np.array([1.0, 1.0, 0.1])
    labels = (1 + (xyz[:, 0] // 5) % 6).astype(np.uint8)
    paths = []
    for name, shift in (("a", 0.0), ("b", 0.02)):
        cloud = PointCloud.from_arrays(xyz + shift, labels=labels)
        points = folder / f"{name}.txt"
        write_ascii_points(points, [cloud], labels_path=folder / f"{name}.labels")
        paths += [points, folder / f"{name}.labels"]
    return paths


def _lower_memory_limit(limit: int, dask_worker: Any = None) -> None:
    """Set a running nanny's memory limit (its monitor reads it every 100 ms)."""
    dask_worker.memory_manager.memory_limit = limit


def test_scan_larger_than_worker_memory(real_cluster: DaskCluster, tmp_path: Path) -> None:
    client = real_cluster.client
    settings = {"max_distance_m": 0.1, "tile_size_m": 3.0}  # 100 tiles of ~2.5 k points
    n_points = 250_000
    scan = _write_pair(tmp_path, n_points)
    # Warm up on a small pair: libraries imported, heap grown to what a tile needs.
    small = tmp_path / "small"
    small.mkdir()
    compute_label_agreement_on_cluster(
        *_write_pair(small, 20_000), cluster=real_cluster, **settings
    )
    scan_bytes = 44 * 2 * n_points  # the two tile stores' point records
    headroom = scan_bytes // 2  # a worker cannot hold the scans
    before = real_cluster.worker_memory()
    for address, (resident, _) in before.items():
        limit = int((resident + headroom) / 0.95)  # the nanny terminates above 95 %
        client.run(_lower_memory_limit, limit, workers=[address], nanny=True)
    try:
        result = compute_label_agreement_on_cluster(*scan, cluster=real_cluster, **settings)
        after = real_cluster.worker_memory()
    finally:
        client.run(_lower_memory_limit, MEMORY_LIMIT, nanny=True)
    assert set(after) == set(before)  # no worker was restarted for its memory
    for address, (resident, _) in after.items():
        assert resident < before[address][0] + headroom < before[address][0] + scan_bytes
    for direction in result.directions:  # B is A moved by 2 cm: every point finds its twin
        assert direction.n_points == direction.n_matched == n_points
        assert np.trace(direction.confusion) > 0.99 * n_points


def test_killed_worker_job_finishes_identical(
    real_cluster: DaskCluster, model: CovarianceModel, scan_dir: Path, tmp_path: Path
) -> None:
    expected = predict_scan(model, scan_dir / "test.txt", out_path=tmp_path / "single.labels")
    client = real_cluster.client
    pids = client.run(os.getpid)  # worker address -> worker process id
    killed: list[str] = []

    def kill_one(done: int, total: int) -> None:
        if done >= 1 and not killed:
            busy = [address for address, keys in client.processing().items() if keys]
            victim = busy[0] if busy else sorted(pids)[0]
            os.killpg(os.getpgid(pids[victim]), signal.SIGKILL)  # the worker and its nanny
            killed.append(victim)

    run = predict_scan(
        ClusterPredictor(model, real_cluster, tile_progress=kill_one),
        scan_dir / "test.txt",
        out_path=tmp_path / "cluster.labels",
    )
    assert killed
    assert killed[0] not in client.scheduler_info()["workers"]  # that worker is gone
    assert filecmp.cmp(expected.labels_path, run.labels_path, shallow=False)


def _allocator_state() -> tuple[str | None, int | None]:
    from semantic3d.scale import cluster as cluster_module

    return os.environ.get("MALLOC_TRIM_THRESHOLD_"), cluster_module._LIMITED.get("allocator")


def test_workers_get_the_allocator_thresholds_back(cluster: DaskCluster) -> None:
    """Dask's nanny sets MALLOC_TRIM_THRESHOLD_; the first task undoes its cost (glibc)."""
    list(cluster.map(abs, [1, 2, 3, 4]))
    states = cluster.client.run(_allocator_state)
    assert len(states) == 2
    for variable, relaxed in states.values():
        assert variable is not None  # the nanny's environment, which made tiles 1.7x slower
        if sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc":
            assert relaxed == 1


def test_the_allocator_is_left_alone_outside_a_worker(monkeypatch: pytest.MonkeyPatch) -> None:
    from semantic3d.scale.cluster import relax_allocator

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    assert relax_allocator() is False
