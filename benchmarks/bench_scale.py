"""Scale-out on Dask: covariance prediction on 1 and 2 local workers against one process.

In one run, on one simulated scan (``--points``, default 200 k, street scene; tiles of
``--tile-size``, default 25.6 m as in the baseline's configuration):

- single: :func:`semantic3d.baselines.covariance.predict.predict_scan`, the path a user
  gets without ``--workers`` (numba uses every core), and the same with numba / BLAS
  limited to one thread (what one single-threaded worker has);
- tiling: the part the client does alone on a cluster (stream the scan into the tile
  store, build the pyramids: ``TiledScan``), timed apart (Amdahl's serial part);
- 1 worker, 2 workers: :func:`semantic3d.scale.predict.predict_scan_on_cluster` on a
  ``LocalCluster`` of single-threaded worker processes (started and warmed up before the
  clock starts); the labels are checked byte for byte against the single run;
- per-task overhead: a no-op mapped over ``--tasks`` items on one worker
  (:meth:`DaskCluster.map`), wall time per task;
- training features (``--train-points`` per class over two simulated scans of
  ``--points`` each): :func:`build_training_set` in one process against
  :func:`semantic3d.scale.training.build_training_set_on_cluster` on 1 and 2 workers
  (arrays checked equal);
- CNN prediction (``--cnn-points``, the default configuration's 5 scales of 16³ cubes,
  an untrained network: its cost does not depend on the weights): one process against
  :class:`semantic3d.scale.predict_cnn.ClusterCnnPredictor` on 1 and 2 workers (labels
  checked byte for byte); ``--cnn-points 0`` leaves it out.

Wall seconds, CPU seconds (this process plus the workers) and points/s. The machine's
load is printed: timings on a loaded machine are noisy, compare rows of one run only.
Writes ``benchmarks/out/bench_scale.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import filecmp
import json
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"


def _noop(item: int) -> int:
    return item


def _worker_cpu() -> float:
    return time.process_time()


def _config(tile_size_m: float) -> Any:
    from semantic3d.baselines.covariance.config import (
        CovarianceConfig,
        ForestConfig,
        PredictionConfig,
        SamplingConfig,
    )
    from semantic3d.features import FeatureConfig

    return CovarianceConfig(
        features=FeatureConfig(base_voxel_size_m=0.1, n_levels=6, k_neighbours=10),
        forest=ForestConfig(n_estimators=20, max_depth=15),
        sampling=SamplingConfig(points_per_class=800, seed=0),
        prediction=PredictionConfig(tile_size_m=tile_size_m, max_points_in_memory=0),
    )


def _timed(run: Callable[[], Any], cluster: Any = None) -> tuple[Any, float, float]:
    """``(value, wall_s, cpu_s)``; CPU of this process plus the cluster's workers."""

    def workers() -> float:
        return 0.0 if cluster is None else sum(cluster.client.run(_worker_cpu).values())

    cpu, before, wall = time.process_time(), workers(), time.perf_counter()
    value = run()
    elapsed = time.perf_counter() - wall
    return value, elapsed, time.process_time() - cpu + workers() - before


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=200_000)
    parser.add_argument("--tasks", type=int, default=400)
    parser.add_argument("--train-points", type=int, default=20_000, help="Per class.")
    parser.add_argument("--cnn-points", type=int, default=4_000)
    parser.add_argument(
        "--tile-size", type=float, default=25.6, help="Tile edge in metres (the default's)."
    )
    args = parser.parse_args()

    from semantic3d.baselines.covariance.predict import predict_scan
    from semantic3d.baselines.covariance.training import (
        build_training_set,
        find_labelled_scans,
        fit_model,
    )
    from semantic3d.datasets.simulator import simulate
    from semantic3d.features.tiling import TiledScan
    from semantic3d.io.formats import iter_points
    from semantic3d.scale.cluster import ClusterSpec, connect, limit_threads
    from semantic3d.scale.predict import predict_scan_on_cluster

    print(f"load average {os.getloadavg()}, {os.cpu_count()} cores")
    rows: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as scratch:
        folder = Path(scratch)
        train = simulate("village", out=folder / "train", n_points=60_000, seed=1).scans[0]
        scan = simulate("street", out=folder / "scan", n_points=args.points, seed=2).scans[0]
        small = simulate("street", out=folder / "small", n_points=10_000, seed=3).scans[0]
        config = _config(args.tile_size)
        (folder / "labelled").mkdir()
        for path in (train.points_path, train.labels_path):
            path.rename(folder / "labelled" / path.name)
        scans = find_labelled_scans(folder / "labelled")
        model = fit_model(build_training_set(scans, config=config), config=config)
        n_points = scan.n_points

        def record(name: str, wall: float, cpu: float) -> None:
            rows[name] = {"wall_s": wall, "cpu_s": cpu, "points_per_s": n_points / wall}
            print(f"{name:28s} {wall:8.2f} s wall {cpu:8.2f} s CPU {n_points / wall:12,.0f} pts/s")

        predict_scan(model, small.points_path, out_path=folder / "warm.labels")
        _, wall, cpu = _timed(
            lambda: predict_scan(model, scan.points_path, out_path=folder / "single.labels")
        )
        record("single process (all cores)", wall, cpu)
        limit_threads(1)
        _, wall, cpu = _timed(
            lambda: predict_scan(model, scan.points_path, out_path=folder / "single1.labels")
        )
        record("single process (1 thread)", wall, cpu)

        def tile_only() -> int:
            chunks = iter_points(scan.points_path, chunk_size=1 << 20, sibling_labels=False)
            with TiledScan(
                chunks,
                config=config.features,
                tile_size_m=config.prediction.tile_size_m,
                workdir=folder,
            ) as tiled:
                return len(tiled.tiles)

        n_tiles, wall, cpu = _timed(tile_only)
        record("client part (tile store)", wall, cpu)
        rows["client part (tile store)"]["n_tiles"] = n_tiles

        for n_workers in (1, 2):
            with connect(ClusterSpec(n_workers=n_workers, threads_per_worker=1)) as cluster:
                out = folder / f"cluster{n_workers}.labels"
                predict_scan_on_cluster(
                    model,
                    small.points_path,
                    cluster=cluster,
                    out_path=folder / "w.labels",
                    overwrite=True,
                )  # warm up: imports and compiled kernels in every worker
                _, wall, cpu = _timed(
                    lambda cluster=cluster, out=out: predict_scan_on_cluster(
                        model, scan.points_path, cluster=cluster, out_path=out
                    ),
                    cluster,
                )
                record(f"{n_workers} worker(s)", wall, cpu)
                assert filecmp.cmp(folder / "single.labels", out, shallow=False)
                if n_workers == 1:
                    list(cluster.map(_noop, list(range(50))))
                    _, wall, cpu = _timed(
                        lambda cluster=cluster: list(cluster.map(_noop, list(range(args.tasks)))),
                        cluster,
                    )
                    rows["per-task overhead"] = {
                        "wall_ms": 1000 * wall / args.tasks,
                        "cpu_ms": 1000 * cpu / args.tasks,
                    }
                    print(f"per-task overhead {1000 * wall / args.tasks:.2f} ms wall")
        _bench_training(folder, args, rows)
        if args.cnn_points:
            _bench_cnn(folder, args, rows)
    single = rows["single process (all cores)"]["wall_s"]
    single1 = rows["single process (1 thread)"]["wall_s"]
    summary = {
        "one_worker_overhead_vs_single": rows["1 worker(s)"]["wall_s"] / single - 1,
        "one_worker_overhead_vs_single_1_thread": rows["1 worker(s)"]["wall_s"] / single1 - 1,
        "two_worker_speedup_vs_single": single / rows["2 worker(s)"]["wall_s"],
        "two_worker_speedup_vs_one_worker": rows["1 worker(s)"]["wall_s"]
        / rows["2 worker(s)"]["wall_s"],
        "worker_cpu_s_per_point": (rows["1 worker(s)"]["cpu_s"]) / n_points,
        "client_s_per_point": rows["client part (tile store)"]["wall_s"] / n_points,
    }
    for job in ("train features", "cnn predict"):
        if f"{job}: single process" in rows:
            one, two = rows[f"{job}: 1 worker(s)"]["wall_s"], rows[f"{job}: 2 worker(s)"]["wall_s"]
            alone = rows[f"{job}: single process"]["wall_s"]
            summary[f"{job}: one worker overhead"] = one / alone - 1
            summary[f"{job}: two worker speed-up vs single"] = alone / two
            summary[f"{job}: two worker speed-up vs one worker"] = one / two
    for key, value in summary.items():
        print(f"{key:40s} {value:.4g}")
    OUT.mkdir(parents=True, exist_ok=True)
    result = {
        "points": n_points,
        "tile_size_m": args.tile_size,
        "load_average": os.getloadavg(),
        "cpu_count": os.cpu_count(),
        "config": dataclasses.asdict(config.prediction),
        "rows": rows,
        "summary": summary,
    }
    (OUT / "bench_scale.json").write_text(json.dumps(result, indent=2) + "\n")


def _record(rows: dict[str, dict[str, float]], name: str, wall: float, cpu: float, n: int) -> None:
    rows[name] = {"wall_s": wall, "cpu_s": cpu, "points_per_s": n / wall}
    print(f"{name:36s} {wall:8.2f} s wall {cpu:8.2f} s CPU {n / wall:12,.0f} pts/s")


def _bench_training(
    folder: Path, args: argparse.Namespace, rows: dict[str, dict[str, float]], **_: Any
) -> None:
    """Training features of two scans: one process against 1 and 2 workers."""
    import numpy as np

    from semantic3d.baselines.covariance.training import build_training_set, find_labelled_scans
    from semantic3d.datasets.simulator import simulate
    from semantic3d.scale.cluster import ClusterSpec, connect
    from semantic3d.scale.training import build_training_set_on_cluster

    labelled = folder / "training"
    for name, scene, seed in (("a", "street", 5), ("b", "village", 6)):
        scan = simulate(scene, out=folder / f"sim-{name}", n_points=args.points, seed=seed).scans[0]
        labelled.mkdir(exist_ok=True)
        for path in (scan.points_path, scan.labels_path):
            path.rename(labelled / f"{name}{path.suffix}")
    scans = find_labelled_scans(labelled)
    config = _config(args.tile_size)
    config = dataclasses.replace(
        config,
        sampling=dataclasses.replace(config.sampling, points_per_class=args.train_points),
    )
    n_points = sum(1 for _ in (labelled / "a.labels").open()) + sum(
        1 for _ in (labelled / "b.labels").open()
    )
    single, wall, cpu = _timed(lambda: build_training_set(scans, config=config))
    _record(rows, "train features: single process", wall, cpu, n_points)
    for n_workers in (1, 2):
        with connect(ClusterSpec(n_workers=n_workers, threads_per_worker=1)) as cluster:
            build_training_set_on_cluster(  # warm up the workers
                scans[:1],
                config=dataclasses.replace(
                    config, sampling=dataclasses.replace(config.sampling, points_per_class=50)
                ),
                cluster=cluster,
            )
            found, wall, cpu = _timed(
                lambda cluster=cluster: build_training_set_on_cluster(
                    scans, config=config, cluster=cluster
                ),
                cluster,
            )
            _record(rows, f"train features: {n_workers} worker(s)", wall, cpu, n_points)
            assert np.array_equal(found.features, single.features)
            assert np.array_equal(found.labels, single.labels)
    rows["train features: single process"]["training_rows"] = float(single.labels.size)


def _bench_cnn(folder: Path, args: argparse.Namespace, rows: dict[str, dict[str, float]]) -> None:
    """CNN prediction: one process against 1 and 2 workers (the default configuration)."""
    import torch

    from semantic3d.baselines.cnn.config import CnnConfig
    from semantic3d.baselines.cnn.model import CnnModel
    from semantic3d.baselines.cnn.network import build_network
    from semantic3d.baselines.common.prediction import predict_scan
    from semantic3d.datasets.simulator import simulate
    from semantic3d.scale.cluster import ClusterSpec, connect, limit_threads
    from semantic3d.scale.predict_cnn import ClusterCnnPredictor

    scan = simulate("street", out=folder / "cnn", n_points=args.cnn_points, seed=7).scans[0]
    warm = simulate("street", out=folder / "cnn-warm", n_points=300, seed=8).scans[0]
    config = CnnConfig()
    torch.manual_seed(0)
    model = CnnModel(
        build_network(config.cubes, config.network),
        config=config,
        label_values=(1, 2, 3, 4, 5, 6, 8),
        training_scans=(),
        seed=0,
        n_batches_trained=0,
        training_time_s=0.0,
        package_version="bench",
    )
    limit_threads(1)  # what one single-threaded worker has
    predict_scan(model, warm.points_path, out_path=folder / "cnn-warm.labels")
    _, wall, cpu = _timed(
        lambda: predict_scan(model, scan.points_path, out_path=folder / "cnn-single.labels")
    )
    _record(rows, "cnn predict: single process", wall, cpu, scan.n_points)
    for n_workers in (1, 2):
        with connect(ClusterSpec(n_workers=n_workers, threads_per_worker=1)) as cluster:
            predictor = ClusterCnnPredictor(model, cluster)
            predict_scan(predictor, warm.points_path, out_path=folder / f"cnn-w{n_workers}.labels")
            out = folder / f"cnn-cluster{n_workers}.labels"
            _, wall, cpu = _timed(
                lambda predictor=predictor, out=out: predict_scan(
                    predictor, scan.points_path, out_path=out
                ),
                cluster,
            )
            _record(rows, f"cnn predict: {n_workers} worker(s)", wall, cpu, scan.n_points)
            assert filecmp.cmp(folder / "cnn-single.labels", out, shallow=False)


if __name__ == "__main__":
    main()
