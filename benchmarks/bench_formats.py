"""Throughput and peak memory of the LAS, LAZ, PLY and cache readers and writers against the
plain laspy / plyfile / numpy calls a user would write instead, in one run, on the same data.
Each contender runs in its own process so peak RSS is its own.

    python benchmarks/bench_formats.py [--points 5000000]

The source points (georeferenced millimetre coordinates, signed intensities, labels) are
generated once into a cache under benchmarks/out/; every writer reads them from there
(ours chunk by chunk, the plain calls whole, as their APIs need), every reader reads the
file the matching writer of ours produced.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import OUT, Measurement, emit, measure_here, measure_in_child, table

HERE = Path(__file__).resolve()
ORIGIN = np.array([870_000.0, 6_617_000.0, 0.0])


def make_source(n_points: int) -> Path:
    from semantic3d.core import PointCloud
    from semantic3d.io.cache import write_cache

    path = OUT / f"formats_{n_points}.cache"
    if (path / "meta.json").is_file():
        return path
    OUT.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)

    def chunks() -> Iterator[PointCloud]:
        step = 1 << 20
        for start in range(0, n_points, step):
            n = min(step, n_points - start)
            yield PointCloud.from_arrays(
                np.round(ORIGIN + rng.uniform(0.0, 500.0, (n, 3)), 3),
                intensity=rng.integers(-2048, 2048, n),
                rgb=rng.integers(0, 256, (n, 3)),
                labels=rng.integers(0, 9, n),
            )

    write_cache(path, chunks())
    return path


def _plain_las_write(source: Path, target: Path) -> int:
    """What a user writes with laspy alone: everything in memory, one ``write``."""
    import laspy

    from semantic3d.io.cache import read_cache

    cloud = read_cache(source)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.full(3, 0.001)
    header.offsets = np.floor(cloud.xyz.min(axis=0))
    header.add_extra_dims(
        [
            laspy.ExtraBytesParams("semantic3d_intensity", np.int32),
            laspy.ExtraBytesParams("label", np.uint8),
        ]
    )
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.xyz.T
    las.intensity = np.clip(cloud.intensity + 2048, 0, 65535).astype(np.uint16)
    las.semantic3d_intensity = cloud.intensity
    las.red, las.green, las.blue = (cloud.rgb.astype(np.uint16) * 257).T
    las.label = cloud.labels
    las.write(target)
    return cloud.n_points


def _plain_las_read(path: Path) -> int:
    import laspy

    las = laspy.read(path)  # then the columns a PointCloud holds, as arrays
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    _rgb = np.stack([las.red >> 8, las.green >> 8, las.blue >> 8], axis=1).astype(np.uint8)
    _labels = np.array(las.label)
    return int(xyz.shape[0])


def _plain_ply_write(source: Path, target: Path) -> int:
    import plyfile

    from semantic3d.io.cache import read_cache

    cloud = read_cache(source)
    vertices = np.empty(
        cloud.n_points,
        dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("intensity", "<i4"),
               ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("scalar_label", "u1")],
    )  # fmt: skip
    vertices["x"], vertices["y"], vertices["z"] = cloud.xyz.T
    vertices["intensity"] = cloud.intensity
    vertices["red"], vertices["green"], vertices["blue"] = cloud.rgb.T
    vertices["scalar_label"] = cloud.labels
    plyfile.PlyData([plyfile.PlyElement.describe(vertices, "vertex")]).write(str(target))
    return cloud.n_points


def _plain_ply_read(path: Path) -> int:
    import plyfile

    vertices = plyfile.PlyData.read(str(path))["vertex"].data  # the default call
    xyz = np.stack([vertices["x"], vertices["y"], vertices["z"]], axis=1)
    _labels = np.array(vertices["scalar_label"])
    return int(xyz.shape[0])


def _plain_numpy_write(source: Path, target: Path) -> int:
    from semantic3d.io.cache import read_cache

    cloud = read_cache(source)
    target.mkdir(exist_ok=True)
    for name in ("xyz", "intensity", "rgb", "labels"):
        np.save(target / f"{name}.npy", getattr(cloud, name))
    return cloud.n_points


def _plain_numpy_read(path: Path) -> int:
    arrays = {name: np.load(path / f"{name}.npy") for name in ("xyz", "intensity", "rgb", "labels")}
    return int(arrays["xyz"].shape[0])


def run_contender(name: str, source: Path, target: Path) -> Measurement:
    # Import everything before the clock starts: import time is not throughput.
    import laspy  # noqa: F401
    import plyfile  # noqa: F401

    import semantic3d.io.las
    import semantic3d.io.ply  # noqa: F401
    from semantic3d.io.formats import iter_points, write_points

    if target.is_dir():
        shutil.rmtree(target)
    if name.startswith("semantic3d.write"):
        return measure_here(name, lambda: write_points(target, iter_points(source)))
    if name.startswith("semantic3d.iter"):
        return measure_here(name, lambda: sum(c.n_points for c in iter_points(source)))
    plain = {
        "laspy.LasData.write (whole)": lambda: _plain_las_write(source, target),
        "laspy.read (whole)": lambda: _plain_las_read(source),
        "plyfile.PlyData.write (whole)": lambda: _plain_ply_write(source, target),
        "plyfile.PlyData.read (whole)": lambda: _plain_ply_read(source),
        "numpy.save per column": lambda: _plain_numpy_write(source, target),
        "numpy.load per column": lambda: _plain_numpy_read(source),
    }
    if name not in plain:
        raise SystemExit(f"unknown contender {name}")
    return measure_here(name, plain[name])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--points", type=int, default=5_000_000)
    parser.add_argument("--child", nargs=3, metavar=("NAME", "SOURCE", "TARGET"))
    args = parser.parse_args()
    if args.child:
        emit(run_contender(args.child[0], Path(args.child[1]), Path(args.child[2])))
        return

    source = make_source(args.points)
    # Warm the page cache so every contender reads from memory.
    for column in source.glob("*.npy"):
        with column.open("rb") as stream:
            while stream.read(64 << 20):
                pass
    print(f"{args.points:,} points, georeferenced (x ≈ 870 000 m), with labels")
    cases = [
        ("LAS", ".las", "laspy.LasData.write (whole)", "laspy.read (whole)"),
        ("LAZ", ".laz", "laspy.LasData.write (whole)", "laspy.read (whole)"),
        ("PLY", ".ply", "plyfile.PlyData.write (whole)", "plyfile.PlyData.read (whole)"),
        ("cache", ".cache", "numpy.save per column", "numpy.load per column"),
    ]
    for label, suffix, plain_write, plain_read in cases:
        ours = OUT / f"formats_{args.points}_ours{suffix}"
        theirs = OUT / f"formats_{args.points}_plain{suffix}"
        writes = [
            measure_in_child(HERE, f"semantic3d.write_points → {label}", str(source), str(ours)),
            measure_in_child(HERE, plain_write, str(source), str(theirs)),
        ]
        reads = [
            measure_in_child(HERE, f"semantic3d.iter_points ← {label}", str(ours), "-"),
            measure_in_child(HERE, plain_read, str(ours), "-"),
        ]
        size_mb = (
            sum(p.stat().st_size for p in ([ours] if ours.is_file() else ours.iterdir())) / 1e6
        )
        print()
        print(table(f"{label} write ({size_mb:.0f} MB)", "points", writes, plain_write))
        print(table(f"{label} read", "points", reads, plain_read))
    from semantic3d.io.cache import open_cache

    start = time.perf_counter()
    scan = open_cache(OUT / f"formats_{args.points}_ours.cache")
    print(f"\nopen_cache of {scan.n_points:,} points: {1e3 * (time.perf_counter() - start):.2f} ms")


if __name__ == "__main__":
    main()
