"""Throughput of the CNN baseline (DeepNet) on CPU: cubes, network, end to end, memory.

Sections (``--only cubes,network,predict``; default all), on a real scan (CMU Oakland,
../shared/data/oakland, 2-9 cm point spacing) with the paper's cubes (5 scales of 16^3
voxels, 2.5-40 cm) and network (5.6 M parameters, untrained: speed does not depend on
the weights):

- cubes: occupancy cubes per second, for both centrings. Corner-centred: the compiled
  sorted-key lookup (:func:`semantic3d.baselines.cnn.fill_cubes`) against what one writes
  without it, in the same run: numpy (every cube voxel's key, ``np.searchsorted`` in the
  sorted keys, batch by batch) and scipy's cKDTree (each point's neighbours within the
  cube, marked one by one); all three give identical cubes (checked). Point-centred (the
  paper's, the default): the compiled per-cell orthant summaries
  (:mod:`semantic3d.baselines.cnn.point_cubes`) against cKDTree neighbours placed with
  the exact formula; identical cubes (checked).
- network: inference points/s of DeepNet, batch 256, ``torch.inference_mode``, in the
  default (NCDHW) layout and channels-last (what the model uses); FLOPs per point and the
  achieved GFLOP/s against the cores' peak.
- predict: end to end (read ASCII, tile store, cubes, network, write ``.labels`` + run
  record) on a crop of a scan, points/s, CPU seconds and peak RSS of a fresh process:
  point-centred cubes with and without classifying identical cubes once, and
  corner-centred ones.

No GPU is available to this work: the CUDA path (cubes filled on the device, bf16
autocast, channels-last, host tiles prefetched while the GPU works) is written and tested
under the ``gpu`` marker only; ``--device cuda`` times it where one exists.
Writes ``benchmarks/out/bench_cnn.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
DATA = ROOT.parent / "shared" / "data" / "oakland"
SCAN = "oakland_part2_ac"


def _load_xyz() -> np.ndarray:
    from semantic3d.io.formats import read_points

    return np.asarray(read_points(DATA / f"{SCAN}.txt").xyz)


def _timed(run: Any) -> tuple[Any, float, float]:
    cpu, wall = time.process_time(), time.perf_counter()
    value = run()
    return value, time.perf_counter() - wall, time.process_time() - cpu


def numpy_cubes(keys: tuple[np.ndarray, ...], corners: np.ndarray, size: int) -> np.ndarray:
    """Every cube voxel's key looked up with np.searchsorted (batches of 64 points)."""
    from semantic3d.spatial.voxels import pack_keys

    axis = np.arange(size)
    offsets = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    out = np.zeros((corners.shape[0], len(keys), size, size, size), np.float32)
    for begin in range(0, corners.shape[0], 64):
        part = corners[begin : begin + 64]
        for scale, sorted_keys in enumerate(keys):
            cells = (part[:, scale, None, :] + offsets).reshape(-1, 3)
            packed = pack_keys(cells)
            found = np.minimum(np.searchsorted(sorted_keys, packed), sorted_keys.size - 1)
            hit = sorted_keys[found] == packed
            out[begin : begin + 64, scale] = hit.reshape(-1, size, size, size)
    return out


def tree_cubes(
    xyz: np.ndarray, queries: np.ndarray, origin: np.ndarray, sizes: tuple[float, ...], size: int
) -> np.ndarray:
    """Each point's neighbours from a k-d tree, marked into its cubes one by one."""
    from scipy.spatial import cKDTree

    from semantic3d.baselines.cnn.cubes import compute_corner_cells

    tree = cKDTree(xyz)
    corners = compute_corner_cells(queries, origin=origin, voxel_sizes_m=sizes, cube_voxels=size)
    out = np.zeros((queries.shape[0], len(sizes), size, size, size), np.float32)
    for scale, voxel in enumerate(sizes):
        cells_all = np.floor((xyz - origin) / voxel).astype(np.int64)
        near = tree.query_ball_point(queries, r=(size / 2 + 1) * voxel, p=np.inf)
        for q, neighbours in enumerate(near):
            cells = cells_all[neighbours] - corners[q, scale]
            inside = np.all((cells >= 0) & (cells < size), axis=1)
            i, j, k = cells[inside].T
            out[q, scale, i, j, k] = 1.0
    return out


def tree_point_cubes(
    xyz: np.ndarray, queries: np.ndarray, origin: np.ndarray, sizes: tuple[float, ...], size: int
) -> np.ndarray:
    """Point-centred cubes: each point's neighbours from a k-d tree, placed by the exact
    integer/fraction formula of :mod:`semantic3d.baselines.cnn.point_cubes`."""
    from scipy.spatial import cKDTree

    tree = cKDTree(xyz)
    out = np.zeros((queries.shape[0], len(sizes), size, size, size), np.float32)
    for scale, voxel in enumerate(sizes):
        scaled = (xyz - origin) / voxel
        cells = np.floor(scaled)
        fractions = scaled - cells
        q_scaled = (queries - origin) / voxel
        q_cells = np.floor(q_scaled)
        q_fractions = q_scaled - q_cells
        near = tree.query_ball_point(queries, r=(size / 2 + 0.5) * voxel, p=np.inf)
        for q, neighbours in enumerate(near):
            index = (cells[neighbours] - q_cells[q]).astype(np.int64) + size // 2
            index -= fractions[neighbours] < q_fractions[q]
            inside = np.all((index >= 0) & (index < size), axis=1)
            i, j, k = index[inside].T
            out[q, scale, i, j, k] = 1.0
    return out


def dense_surfaces(spacing_m: float = 0.01) -> np.ndarray:
    """A dense static scan's worst case: 6 x 6 m of ground and a 3 x 3 m plane tilted
    against all three axes (its own skyline), both sampled every ``spacing_m`` with 2 mm
    noise (450,000 points at 1 cm)."""
    rng = np.random.default_rng(0)
    grid = np.mgrid[0:6:spacing_m, 0:6:spacing_m].reshape(2, -1).T
    ground = np.column_stack([grid, rng.normal(0, 0.002, len(grid))])
    plane = np.mgrid[0:3:spacing_m, 0:3:spacing_m].reshape(2, -1).T
    a = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
    b = np.array([1.0, 1.0, -2.0]) / np.sqrt(6)
    normal = np.ones(3) / np.sqrt(3)
    tilted = (
        plane[:, :1] * a + plane[:, 1:] * b + 2.0 + rng.normal(0, 0.002, (len(plane), 1)) * normal
    )
    return np.concatenate([ground, tilted])


def bench_point_cubes(xyz: np.ndarray, n_queries: int) -> dict[str, Any]:
    """Point-centred cubes: the compiled kernel against the cKDTree reference, and
    corner-centred ones, same run, same points."""
    from semantic3d.baselines.cnn.config import CubeConfig
    from semantic3d.baselines.cnn.cubes import build_occupancy, compute_cubes
    from semantic3d.spatial.voxels import grid_origin

    cubes = CubeConfig(centring="point")
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=max(cubes.voxel_sizes_m))
    queries = xyz[np.random.default_rng(0).choice(len(xyz), n_queries, replace=False)]
    corner = build_occupancy(xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m)
    compute_cubes(corner, queries[:8], cube_voxels=16, centring="corner")  # compiled
    _, corner_s, corner_cpu = _timed(
        lambda: compute_cubes(corner, queries, cube_voxels=16, centring="corner")
    )
    build_occupancy(xyz[:1000], origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring="point")
    occupancy, occ_s, occ_cpu = _timed(
        lambda: build_occupancy(
            xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring="point"
        )
    )
    assert occupancy.summaries is not None
    compute_cubes(occupancy, queries[:8], cube_voxels=16, centring="point")  # compiled
    ours, ours_s, ours_cpu = _timed(
        lambda: compute_cubes(occupancy, queries, cube_voxels=16, centring="point")
    )
    few = max(n_queries // 10, 1)
    tree, tree_s, tree_cpu = _timed(
        lambda: tree_point_cubes(xyz, queries[:few], origin, cubes.voxel_sizes_m, 16)
    )
    assert np.array_equal(ours[:few], tree)
    return {
        "scan_points": len(xyz),
        "occupancy_build_s": occ_s,
        "occupancy_build_cpu_s": occ_cpu,
        "summary_rows_per_scale": [int(s.fractions.shape[0]) for s in occupancy.summaries],
        "occupied_cells_per_scale": [int(k.size) for k in occupancy.keys],
        "fill_point_cubes": {"points": n_queries, "wall_s": ours_s, "cpu_s": ours_cpu},
        "fill_corner_cubes": {"points": n_queries, "wall_s": corner_s, "cpu_s": corner_cpu},
        "ckdtree_point": {"points": few, "wall_s": tree_s, "cpu_s": tree_cpu},
        "occupancy": float(ours.mean()),
    }


def bench_cubes(n_queries: int) -> dict[str, Any]:
    from semantic3d.baselines.cnn.config import CubeConfig
    from semantic3d.baselines.cnn.cubes import build_occupancy, compute_corner_cells, fill_cubes
    from semantic3d.spatial.voxels import grid_origin

    cubes = CubeConfig()
    xyz = _load_xyz()
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=max(cubes.voxel_sizes_m))
    queries = xyz[np.random.default_rng(0).choice(len(xyz), n_queries, replace=False)]
    occupancy, occ_s, occ_cpu = _timed(
        lambda: build_occupancy(xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m)
    )
    corners = compute_corner_cells(
        queries, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, cube_voxels=16
    )
    fill_cubes(occupancy, corners[:8], cube_voxels=16)  # compiled / loaded from cache
    ours, ours_s, ours_cpu = _timed(lambda: fill_cubes(occupancy, corners, cube_voxels=16))
    plain, plain_s, plain_cpu = _timed(lambda: numpy_cubes(occupancy.keys, corners, 16))
    few = max(n_queries // 10, 1)
    tree, tree_s, tree_cpu = _timed(
        lambda: tree_cubes(xyz, queries[:few], origin, cubes.voxel_sizes_m, 16)
    )
    assert np.array_equal(ours, plain) and np.array_equal(ours[:few], tree)
    return {
        "scan_points": len(xyz),
        "occupancy_build_s": occ_s,
        "occupancy_build_cpu_s": occ_cpu,
        "fill_cubes": {"points": n_queries, "wall_s": ours_s, "cpu_s": ours_cpu},
        "numpy_searchsorted": {"points": n_queries, "wall_s": plain_s, "cpu_s": plain_cpu},
        "ckdtree": {"points": few, "wall_s": tree_s, "cpu_s": tree_cpu},
        "occupancy": float(ours.mean()),
    }


def network_flops(channels: tuple[int, ...] = (16, 32, 64), size: int = 16) -> int:
    """Multiply-adds x 2 of one point's forward pass (convolutions + linear layers)."""
    macs, previous, side = 0, 1, size
    for width in channels:
        macs += side**3 * width * previous * 27
        previous, side = width, side // 2
    macs *= 5
    macs += 2560 * 2048 + 2048 * 8
    return 2 * macs


def bench_network(batch: int, repeat: int) -> dict[str, Any]:
    import torch

    from semantic3d.baselines.cnn.config import CnnConfig
    from semantic3d.baselines.cnn.network import build_network

    config = CnnConfig()
    torch.manual_seed(0)
    network = build_network(config.cubes, config.network).eval()
    cubes = (torch.rand(batch, 5, 16, 16, 16) < 0.05).float()
    result: dict[str, Any] = {"batch": batch, "threads": torch.get_num_threads()}
    with torch.inference_mode():
        for layout in ("ncdhw", "channels_last"):
            if layout == "channels_last":
                network = network.to(memory_format=torch.channels_last_3d)
            network(cubes[:8])
            best = None
            for _ in range(repeat):
                _, wall, cpu = _timed(lambda net=network: net(cubes))
                if best is None or wall < best[0]:
                    best = (wall, cpu)
            assert best is not None
            result[layout] = {"wall_s": best[0], "cpu_s": best[1]}
    result["flops_per_point"] = network_flops()
    return result


def _crop(path: Path, out: Path, edge_m: float) -> int:
    from semantic3d.io.ascii import write_ascii_points
    from semantic3d.io.formats import read_points

    cloud = read_points(path)
    xy = np.asarray(cloud.xyz)[:, :2]
    low = xy.min(axis=0)
    keep = np.all(xy < low + edge_m, axis=1)
    write_ascii_points(out, [cloud[keep]])
    return int(keep.sum())


def child_predict(scan: str, deduplicate: str, centring: str) -> None:
    """In a fresh process: predict ``scan`` end to end; print a JSON measurement."""
    import dataclasses

    import torch

    from semantic3d import __version__
    from semantic3d.baselines.cnn.config import CnnConfig
    from semantic3d.baselines.cnn.model import CnnModel
    from semantic3d.baselines.cnn.network import build_network
    from semantic3d.baselines.common.prediction import predict_scan

    base = CnnConfig()
    config = dataclasses.replace(
        base,
        cubes=dataclasses.replace(base.cubes, centring=centring),
        prediction=dataclasses.replace(base.prediction, deduplicate=deduplicate == "on"),
    )
    torch.manual_seed(0)
    model = CnnModel(
        build_network(config.cubes, config.network),
        config=config,
        label_values=tuple(range(1, 9)),
        training_scans=(),
        seed=0,
        n_batches_trained=0,
        training_time_s=0.0,
        package_version=__version__,
    )
    with tempfile.TemporaryDirectory() as scratch:
        cpu = time.process_time()
        run = predict_scan(model, scan, out_path=Path(scratch) / "out.labels")
        cpu = time.process_time() - cpu
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        json.dumps(
            {"points": run.n_points, "wall_s": run.runtime_s, "cpu_s": cpu, "peak_rss_mb": peak}
        )
    )


def bench_predict(edge_m: float) -> dict[str, Any]:
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as scratch:
        crop = Path(scratch) / "crop.txt"
        results["points"] = _crop(DATA / f"{SCAN}.txt", crop, edge_m)
        for dedup, centring in (("on", "point"), ("off", "point"), ("on", "corner")):
            done = subprocess.run(
                [sys.executable, __file__, "--child", str(crop), dedup, centring],
                check=True,
                capture_output=True,
                text=True,
                env={**os.environ},
            )
            measured = json.loads(done.stdout.strip().splitlines()[-1])
            results[f"{centring}_deduplicate_{dedup}"] = measured
    return results


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child_predict(sys.argv[2], sys.argv[3], sys.argv[4])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="cubes,network,predict")
    parser.add_argument("--queries", type=int, default=2000, help="points whose cubes are made")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--crop-m", type=float, default=6.0, help="edge of the predicted crop")
    args = parser.parse_args()
    if not DATA.is_dir():
        sys.exit(f"{DATA}: the Oakland samples are not here")
    only = set(args.only.split(","))
    report: dict[str, Any] = {"cpu": os.cpu_count(), "load_average": os.getloadavg()}
    if "cubes" in only:
        report["cubes"] = bench_cubes(args.queries)
        print(json.dumps(report["cubes"], indent=1), flush=True)
        report["point_cubes"] = bench_point_cubes(_load_xyz(), args.queries)
        print(json.dumps(report["point_cubes"], indent=1), flush=True)
        report["point_cubes_dense"] = bench_point_cubes(dense_surfaces(), args.queries // 4)
        print(json.dumps(report["point_cubes_dense"], indent=1), flush=True)
    if "network" in only:
        report["network"] = bench_network(args.batch, args.repeat)
        print(json.dumps(report["network"], indent=1), flush=True)
    if "predict" in only:
        report["predict"] = bench_predict(args.crop_m)
        print(json.dumps(report["predict"], indent=1), flush=True)
    report["load_average_end"] = os.getloadavg()
    OUT.mkdir(exist_ok=True)
    path = OUT / "bench_cnn.json"
    previous = json.loads(path.read_text()) if path.is_file() else {}
    path.write_text(json.dumps({**previous, **report}, indent=2) + "\n")  # sections merge


if __name__ == "__main__":
    main()
