"""Throughput and peak memory of the Semantic3D ASCII and label readers against the
libraries a user would pick instead (pyarrow.csv, pandas, polars), in one run, on the same
files. Each contender runs in its own process so peak RSS is its own.

    python benchmarks/bench_io.py [--points 50000000]

Files are generated once under benchmarks/out/ with the package's writer (benchmark-like
lines: millimetre coordinates, signed intensities, single-digit labels).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import OUT, Measurement, emit, measure_here, measure_in_child, table

HERE = Path(__file__).resolve()
NAMES = ("x", "y", "z", "intensity", "r", "g", "b")


def make_files(n_points: int) -> tuple[Path, Path]:
    from semantic3d.core import PointCloud
    from semantic3d.io import write_ascii_points

    OUT.mkdir(parents=True, exist_ok=True)
    points, labels = OUT / f"scan_{n_points}.txt", OUT / f"scan_{n_points}.labels"
    if points.exists() and labels.exists():
        return points, labels
    rng = np.random.default_rng(0)

    def chunks():  # type: ignore[no-untyped-def]
        step = 1 << 20
        for start in range(0, n_points, step):
            n = min(step, n_points - start)
            xyz = np.round(rng.normal(0.0, 30.0, (n, 3)), 3)
            yield PointCloud.from_arrays(
                xyz,
                intensity=rng.integers(-2048, 2048, n),
                rgb=rng.integers(0, 256, (n, 3)),
                labels=rng.integers(0, 9, n),
            )

    tmp_points, tmp_labels = OUT / (points.name + ".tmp"), OUT / (labels.name + ".tmp")
    write_ascii_points(tmp_points, chunks(), labels_path=tmp_labels)
    tmp_points.rename(points)
    tmp_labels.rename(labels)
    return points, labels


def _warm_up() -> None:
    """Load the compiled kernels (numba's on-disk cache) before the clock starts."""
    from semantic3d.io import read_ascii_points, read_labels

    warm = OUT / "warm.txt"
    warm.write_text("1.0 2.0 3.0 4 5 6 7\n" * 1000)
    read_ascii_points(warm)
    warm_labels = OUT / "warm.labels"
    warm_labels.write_text("1\n" * 1000)
    read_labels(warm_labels)


def run_contender(name: str, path: Path) -> Measurement:
    if name == "semantic3d.iter_ascii_points":
        from semantic3d.io import iter_ascii_points

        _warm_up()
        return measure_here(name, lambda: sum(c.n_points for c in iter_ascii_points(path)))
    if name == "pyarrow.csv.read_csv":
        import pyarrow.csv as pacsv

        read = pacsv.ReadOptions(column_names=list(NAMES), block_size=32 << 20)
        parse = pacsv.ParseOptions(delimiter=" ")
        return measure_here(
            name, lambda: pacsv.read_csv(path, read_options=read, parse_options=parse).num_rows
        )
    if name == "pyarrow.csv.open_csv (stream)":
        import pyarrow.csv as pacsv

        read = pacsv.ReadOptions(column_names=list(NAMES), block_size=32 << 20)
        parse = pacsv.ParseOptions(delimiter=" ")

        def stream() -> int:
            return sum(
                b.num_rows for b in pacsv.open_csv(path, read_options=read, parse_options=parse)
            )

        return measure_here(name, stream)
    if name == "pandas.read_csv (C, chunks)":
        import pandas as pd

        def pandas_points() -> int:
            reader = pd.read_csv(
                path, sep=" ", header=None, names=NAMES, engine="c", chunksize=1 << 20
            )
            return sum(len(frame) for frame in reader)

        return measure_here(name, pandas_points)
    if name == "semantic3d.iter_labels":
        from semantic3d.io import iter_labels

        _warm_up()
        return measure_here(name, lambda: sum(c.size for c in iter_labels(path)))
    if name == "polars.read_csv":
        import polars as pl

        return measure_here(
            name, lambda: pl.read_csv(path, has_header=False, new_columns=["label"]).height
        )
    if name == "pandas.read_csv (labels)":
        import pandas as pd

        return measure_here(
            name, lambda: len(pd.read_csv(path, header=None, engine="c", dtype=np.uint8))
        )
    raise SystemExit(f"unknown contender {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--points", type=int, default=50_000_000)
    parser.add_argument("--child", nargs=2, metavar=("NAME", "PATH"))
    args = parser.parse_args()
    if args.child:
        emit(run_contender(args.child[0], Path(args.child[1])))
        return

    points, labels = make_files(args.points)
    small_points, _ = make_files(args.points // 5)
    # Warm the page cache and the compiled-kernel cache so every contender reads from memory.
    for path in (points, labels, small_points):
        with path.open("rb") as stream:
            while stream.read(64 << 20):
                pass
    measure_in_child(HERE, "semantic3d.iter_labels", str(labels))

    size_gb = points.stat().st_size / 1e9
    print(f"points file: {points.name}, {args.points:,} lines, {size_gb:.2f} GB")
    rows = [
        measure_in_child(HERE, name, str(points))
        for name in (
            "semantic3d.iter_ascii_points",
            "pyarrow.csv.read_csv",
            "pyarrow.csv.open_csv (stream)",
            "pandas.read_csv (C, chunks)",
        )
    ]
    print(table("ASCII points", "points", rows, "pyarrow.csv.read_csv"))
    small = measure_in_child(HERE, "semantic3d.iter_ascii_points", str(small_points))
    print(
        f"peak RSS streaming {args.points // 5:,} points: {small.peak_rss_mb:.0f} MB; "
        f"{args.points:,} points: {rows[0].peak_rss_mb:.0f} MB"
    )
    print()
    rows = [
        measure_in_child(HERE, name, str(labels))
        for name in ("semantic3d.iter_labels", "polars.read_csv", "pandas.read_csv (labels)")
    ]
    print(table("labels (single digit)", "labels", rows, "polars.read_csv"))


if __name__ == "__main__":
    main()
