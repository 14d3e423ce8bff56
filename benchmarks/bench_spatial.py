"""Throughput of the spatial layer: spill a scan into tiles once, then read every tile with a halo.

    python benchmarks/bench_spatial.py [--points 5000000] [--tile 10] [--halo 0.5]

Contenders, each in its own process (wall time and peak RSS of that process):

1. ``TileStore (folder)``: ``build_tile_store`` streams the chunks into a store folder
   (memory-mapped points grouped by tile, sub-cell index), then every tile is read with
   ``read(tile, halo_m=...)``.
2. ``TemporaryTileStore``: the same, held in memory when it fits the buffer (what label
   agreement uses).
3. ``numpy in memory``: what a user writes without the layer: concatenate the scan, sort
   it by tile (``np.lexsort``), then for each tile take its slice and filter the 3 x 3
   neighbouring tiles' slices with a box mask for the halo.

The scan is synthetic (uniform over a square, deterministic chunks of 1 M points), so
the figures are about binning and reading, not parsing. The store's compiled kernels are
loaded before the clock starts. Points/s counts scan points.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import itertools

from _harness import OUT, emit, measure_here, measure_in_child, table

HERE = Path(__file__).resolve()
CHUNK = 1_000_000


def _chunks(n_points: int) -> Iterator:
    from semantic3d.core.pointcloud import PointCloud

    side = float(np.sqrt(n_points / 50.0))  # ~50 points per square metre
    for start in range(0, n_points, CHUNK):
        rng = np.random.default_rng(start)
        n = min(CHUNK, n_points - start)
        xyz = np.column_stack(
            [rng.uniform(0, side, n), rng.uniform(0, side, n), rng.normal(0, 2.0, n)]
        )
        yield PointCloud.from_arrays(xyz, labels=rng.integers(0, 9, n))


def _store(n_points: int, tile: float, halo: float, *, temporary: bool) -> int:
    import shutil

    from semantic3d.spatial import TemporaryTileStore, TileGrid, build_tile_store

    grid = TileGrid.square(tile)
    seen = 0
    if temporary:
        with TemporaryTileStore(_chunks(n_points), grid=grid, buffer_points=1 << 26) as store:
            for data in store.iter_tiles(halo_m=halo):
                seen += data.core.n_points  # the halo is read too (data.halo)
        return seen
    folder = OUT / "spatial-store"
    shutil.rmtree(folder, ignore_errors=True)
    store = build_tile_store(_chunks(n_points), folder, grid=grid)
    for data in store.iter_tiles(halo_m=halo):
        seen += data.core.n_points
    shutil.rmtree(folder, ignore_errors=True)
    return seen


def _numpy(n_points: int, tile: float, halo: float) -> int:
    xyz = np.concatenate([chunk.xyz for chunk in _chunks(n_points)])
    keys = np.floor(xyz[:, :2] / tile).astype(np.int64)
    order = np.lexsort((keys[:, 1], keys[:, 0]))
    xyz, keys = xyz[order], keys[order]
    change = np.flatnonzero(np.any(keys[1:] != keys[:-1], axis=1)) + 1
    starts = np.concatenate(([0], change, [len(xyz)]))
    slices = {
        (int(keys[b, 0]), int(keys[b, 1])): (int(b), int(e)) for b, e in itertools.pairwise(starts)
    }
    seen = 0
    for (ix, iy), (begin, end) in slices.items():
        core = xyz[begin:end]
        x0, y0 = ix * tile - halo, iy * tile - halo
        x1, y1 = (ix + 1) * tile + halo, (iy + 1) * tile + halo
        parts = []
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if (dx, dy) == (0, 0) or (ix + dx, iy + dy) not in slices:
                    continue
                b, e = slices[(ix + dx, iy + dy)]
                other = xyz[b:e]
                inside = (
                    (other[:, 0] >= x0)
                    & (other[:, 0] <= x1)
                    & (other[:, 1] >= y0)
                    & (other[:, 1] <= y1)
                )
                parts.append(other[inside])
        seen += core.shape[0]  # and the halo, in parts
    return seen


def _warm_up() -> None:
    """Load the store's compiled kernels before the clock starts (a one-off ~0.5 s per
    process, as the other benchmarks warm theirs)."""
    from semantic3d.spatial import TemporaryTileStore, TileGrid

    with TemporaryTileStore(_chunks(1000), grid=TileGrid.square(1.0)) as store:
        for _ in store.iter_tiles(halo_m=0.1):
            pass


def child(name: str, n_points: int, tile: float, halo: float) -> None:
    if name != "numpy in memory":
        _warm_up()
    if name == "TileStore (folder)":
        emit(measure_here(name, lambda: _store(n_points, tile, halo, temporary=False)))
    elif name == "TemporaryTileStore":
        emit(measure_here(name, lambda: _store(n_points, tile, halo, temporary=True)))
    elif name == "numpy in memory":
        emit(measure_here(name, lambda: _numpy(n_points, tile, halo)))
    else:
        raise SystemExit(f"unknown contender {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=5_000_000)
    parser.add_argument("--tile", type=float, default=10.0)
    parser.add_argument("--halo", type=float, default=0.5)
    parser.add_argument("--child", default=None)
    parser.add_argument("rest", nargs="*")
    args = parser.parse_args()
    if args.child:
        child(args.child, args.points, args.tile, args.halo)
        return
    OUT.mkdir(parents=True, exist_ok=True)
    options = ["--points", str(args.points), "--tile", str(args.tile), "--halo", str(args.halo)]
    rows = [
        measure_in_child(HERE, name, *options)
        for name in ("TileStore (folder)", "TemporaryTileStore", "numpy in memory")
    ]
    print(
        table(
            f"tile a scan and read every tile with a {args.halo} m halo "
            f"({args.points:,} points, {args.tile} m tiles)",
            "points",
            rows,
            "numpy in memory",
        )
    )


if __name__ == "__main__":
    main()
