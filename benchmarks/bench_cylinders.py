"""Height features of vertical cylinders on a terrestrial scan's pyramid levels.

    python benchmarks/bench_cylinders.py [--points 2000000] [--peer-queries 20000]

A simulated street station (dense walls near the scanner, as a real station) is put in
a voxel pyramid with the default features; the queries are its level-0 voxels, searched
at levels 0, 1 and 2 with their cylinder radii (5, 10 and 20 cm), as a tile's rows are.
Contenders, each in its own process (wall time and peak RSS of that process; the
compiled kernels loaded before the clock starts):

1. ``cylinder_below alone``: the default column, each grid cell read lowest point first,
   only up to its first point inside the radius (``features=("cylinder_below",)``).
2. ``four columns``: every point of the 3 x 3 cells around each query (minimum, maximum
   and count; what the default computed before, then kept one column of).
3. ``scipy cKDTree 2-D``: what a user would write: a 2-D tree of the level's x and y,
   ``query_ball_point`` for each query, the lowest height of the points it lists. It
   runs on the first ``--peer-queries`` queries of each level only (its lists are Python
   objects); its rate is queries per second all the same.

The first two must give the same ``cylinder_below`` bit for bit; the benchmark checks it.
There is no hardware floor to compare with: a search, not a pass over memory.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _harness import emit, measure_here, measure_in_child, table

HERE = Path(__file__).resolve()
LEVELS = (0, 1, 2)


def prepare(n_points: int, folder: Path) -> Path:
    """The station's levels and queries, saved for the contenders' processes."""
    from semantic3d.datasets.simulator import simulate
    from semantic3d.features import FeatureConfig
    from semantic3d.features.pyramid import build_pyramid, grid_origin
    from semantic3d.io.formats import read_points

    config = FeatureConfig()
    scan = simulate("street", out=folder / "scan", n_points=n_points, seed=1).scans[0]
    cloud = read_points(scan.points_path)
    origin = grid_origin(cloud.xyz[0], coarsest_voxel_size_m=config.coarsest_voxel_size_m)
    pyramid = build_pyramid(
        cloud.xyz,
        base_voxel_size_m=config.base_voxel_size_m,
        n_levels=config.n_levels,
        origin=origin,
    )
    path = folder / "levels.npz"
    arrays = {f"level{n}": pyramid.levels[n].xyz for n in LEVELS}
    np.savez(path, queries=pyramid.levels[0].xyz, **arrays)
    return path


def _radius(level: int) -> float:
    from semantic3d.features import FeatureConfig

    return FeatureConfig().cylinder_radius_m(level)


def _ours(path: Path, features: tuple[str, ...]) -> tuple[int, list[np.ndarray]]:
    from semantic3d.features.cylinders import compute_cylinder_features

    data = np.load(path)
    queries = data["queries"]
    columns = []
    for level in LEVELS:
        out = compute_cylinder_features(
            data[f"level{level}"], queries, radius_m=_radius(level), features=features
        )
        columns.append(out[:, features.index("cylinder_below")].copy())
    return queries.shape[0] * len(LEVELS), columns


def _scipy(path: Path, n_queries: int) -> int:
    from scipy.spatial import cKDTree

    data = np.load(path)
    queries = data["queries"][:n_queries]
    for level in LEVELS:
        points = data[f"level{level}"]
        tree = cKDTree(points[:, :2])
        lists = tree.query_ball_point(queries[:, :2], _radius(level), workers=-1)
        below = np.array([queries[i, 2] - points[found, 2].min() for i, found in enumerate(lists)])
        assert below.shape == (queries.shape[0],)
    return queries.shape[0] * len(LEVELS)


def _warm_up() -> None:
    from semantic3d.features.cylinders import CYLINDER_FEATURES, compute_cylinder_features

    points = np.random.default_rng(0).uniform(0.0, 1.0, (500, 3))
    for features in (CYLINDER_FEATURES, ("cylinder_below",)):
        compute_cylinder_features(points, points, radius_m=0.1, features=features)


def child(name: str, path: Path, peer_queries: int) -> None:
    from semantic3d.features.cylinders import CYLINDER_FEATURES

    _warm_up()
    if name == "cylinder_below alone":
        emit(measure_here(name, lambda: _ours(path, ("cylinder_below",))[0]))
    elif name == "four columns":
        emit(measure_here(name, lambda: _ours(path, CYLINDER_FEATURES)[0]))
    elif name == "scipy cKDTree 2-D":
        emit(measure_here(name, lambda: _scipy(path, peer_queries)))
    else:
        raise SystemExit(f"unknown contender {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=2_000_000)
    parser.add_argument("--peer-queries", type=int, default=20_000)
    parser.add_argument("--child", default=None)
    parser.add_argument("--levels", type=Path, default=None)
    args = parser.parse_args()
    if args.child:
        child(args.child, args.levels, args.peer_queries)
        return
    from semantic3d.features.cylinders import CYLINDER_FEATURES

    with tempfile.TemporaryDirectory(prefix="bench-cylinders-") as scratch:
        path = prepare(args.points, Path(scratch))
        below = _ours(path, ("cylinder_below",))[1]
        every = _ours(path, CYLINDER_FEATURES)[1]
        for level, (a, b) in enumerate(zip(below, every, strict=True)):
            if not np.array_equal(a.view(np.uint32), b.view(np.uint32)):
                raise SystemExit(f"level {level}: cylinder_below differs between the kernels")
        n_queries = below[0].shape[0]
        options = ["--levels", str(path), "--peer-queries", str(args.peer_queries)]
        rows = [
            measure_in_child(HERE, name, *options)
            for name in ("cylinder_below alone", "four columns", "scipy cKDTree 2-D")
        ]
    print(
        table(
            f"cylinder_below of {n_queries:,} level-0 voxels at levels 0-2 of a "
            f"{args.points:,}-point street station (the two kernels equal bit for bit)",
            "queries",
            rows,
            "scipy cKDTree 2-D",
        )
    )


if __name__ == "__main__":
    main()
