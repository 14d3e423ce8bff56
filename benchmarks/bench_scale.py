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
  (:meth:`DaskCluster.map`), wall time per task.

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


if __name__ == "__main__":
    main()
