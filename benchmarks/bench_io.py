"""Throughput and peak memory of Semantic3D text IO against what a user would pick instead.

    python benchmarks/bench_io.py [--points 10000000 50000000] [--repeat 2] [--keep]

For each size, benchmark-like files (millimetre coordinates, signed intensities,
single-digit labels) are generated in a temporary folder with the package's writer and
deleted afterwards. Every contender runs in its own process, so its peak RSS is its own,
on the same files, in the same run, from the page cache (files are read once first):

- points: ``semantic3d.io.iter_ascii_points`` vs ``pyarrow.csv.read_csv`` vs pandas' C
  reader (chunked) vs ``polars.read_csv`` (Rust, every core), and the floors: ``cat FILE > /dev/null`` (page cache) and an
  ``O_DIRECT`` read (disk, bypassing the cache);
- labels: ``semantic3d.io.iter_labels`` vs ``polars.read_csv`` vs pandas;
- writing points and labels: the package's writers vs pyarrow ``write_csv`` and pandas
  ``to_csv`` (pandas formats ~0.2 M rows/s: it writes the first 2 M rows only);
- the binary cache: ``iter_cache`` vs ``cat`` of its column files.

The machine is shared, so wall-clock rates move with the load: each table shows the load
average, the median of ``--repeat`` runs with their spread, and CPU seconds per item
(user + system, all threads), which the load disturbs much less.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()
NAMES = ["x", "y", "z", "intensity", "r", "g", "b"]
PANDAS_WRITE_ROWS = 2_000_000
BYTES_PER_POINT = 40  # text (~37.4) + label (2) with room


@dataclass(frozen=True, slots=True)
class Run:
    name: str
    items: int
    seconds: float
    cpu_seconds: float
    peak_rss_mb: float
    load: float

    @property
    def rate(self) -> float:
        return self.items / self.seconds


# --- children -------------------------------------------------------------------------


def _cloud_chunks(n_points: int, seed: int = 0) -> Iterator[object]:
    from semantic3d.core import PointCloud

    rng = np.random.default_rng(seed)
    step = 1 << 20
    for start in range(0, n_points, step):
        n = min(step, n_points - start)
        yield PointCloud.from_arrays(
            np.round(rng.normal(0.0, 30.0, (n, 3)), 3),
            intensity=rng.integers(-2048, 2048, n),
            rgb=rng.integers(0, 256, (n, 3)),
            labels=rng.integers(0, 9, n),
        )


def _in_memory(n_points: int) -> object:
    from semantic3d.core import PointCloud

    return PointCloud.concatenate(list(_cloud_chunks(n_points)))  # type: ignore[arg-type]


def _warm_kernels(name: str, folder: Path) -> None:
    """Load the contender's compiled kernels (numba's on-disk cache) before the clock starts."""
    from semantic3d.core import PointCloud
    from semantic3d.io import read_ascii_points, read_labels, write_ascii_points, write_labels

    warm = folder / f"warm_{os.getpid()}"
    # Larger than the sizes small files are parsed at without the compiled kernels
    # (io._point_text.SMALL_FILE_BYTES, io._label_parsing.SMALL_TEXT_BYTES).
    if name == "semantic3d.iter_ascii_points":
        warm.write_text("1.0 2.0 3.0 4 5 6 7\n" * 100_000)
        read_ascii_points(warm)
    elif name == "semantic3d.iter_labels":
        warm.write_text("1\n" * 1_000_000)
        read_labels(warm)
    elif name == "semantic3d.write_ascii_points":
        write_ascii_points(warm, [PointCloud.from_arrays(np.zeros((1000, 3)))])
    elif name == "semantic3d.write_labels":
        write_labels(warm, [np.ones(1000, np.uint8)])
    warm.unlink(missing_ok=True)


def _timed(run: Callable[[], int], *, shell: bool = False) -> dict[str, float]:
    """Time ``run``; peak RSS is this process's, or the child's for a shell command."""
    before = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    items = run()
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_SELF)
    children_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    cpu += (children_after.ru_utime - children.ru_utime) + (
        children_after.ru_stime - children.ru_stime
    )
    peak_kb = _SHELL_PEAK_KB[-1] if shell else after.ru_maxrss
    return {"items": items, "seconds": seconds, "cpu_seconds": cpu, "peak_rss_mb": peak_kb / 1024}


_SHELL_PEAK_KB: list[int] = []


def _shell(command: str, items: int) -> Callable[[], int]:
    """Run ``command`` under ``/usr/bin/time``: a child's ``ru_maxrss`` would include the
    size of the process that forked it (Linux keeps it across ``exec``)."""

    def run() -> int:
        timed = ["/usr/bin/time", "-f", "%M", "sh", "-c", command]
        result = subprocess.run(
            timed, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
        _SHELL_PEAK_KB.append(int(result.stderr.decode().strip().splitlines()[-1]))
        return items

    return run


def run_contender(name: str, path: Path, n_points: int, folder: Path) -> dict[str, float]:
    """Measure one contender in this (fresh) process."""
    if name == "cat (page cache)":
        return _timed(_shell(f"cat '{path}' > /dev/null", n_points), shell=True)
    if name == "dd O_DIRECT (disk)":
        command = f"dd if='{path}' of=/dev/null bs=16M iflag=direct status=none"
        return _timed(_shell(command, n_points), shell=True)
    if name == "cat cache columns":
        files = " ".join(f"'{p}'" for p in sorted(path.glob("*.npy")))
        return _timed(_shell(f"cat {files} > /dev/null", n_points), shell=True)
    if name == "make files":
        make_files(folder, n_points)
        return {"items": 0, "seconds": 0.0, "cpu_seconds": 0.0, "peak_rss_mb": 0.0}
    if name == "build cache":
        from semantic3d.io.conversion import build_cache

        build_cache(path, folder / "scan.cache", labels_path=path.with_suffix(".labels"))
        return {"items": 0, "seconds": 0.0, "cpu_seconds": 0.0, "peak_rss_mb": 0.0}
    if name.startswith("semantic3d"):
        import semantic3d.io as sio
        from semantic3d.io.cache import iter_cache

        _warm_kernels(name, folder)
    if name == "semantic3d.iter_ascii_points":
        return _timed(lambda: sum(c.n_points for c in sio.iter_ascii_points(path)))
    if name == "pyarrow.csv.read_csv":
        import pyarrow.csv as pacsv

        read = pacsv.ReadOptions(column_names=NAMES, block_size=32 << 20)
        parse = pacsv.ParseOptions(delimiter=" ")
        return _timed(lambda: pacsv.read_csv(path, read_options=read, parse_options=parse).num_rows)
    if name == "polars.read_csv (points)":
        import polars as pl

        def polars_points() -> int:
            frame = pl.read_csv(
                path, has_header=False, separator=" ", new_columns=list(NAMES), low_memory=True
            )
            return frame.height

        return _timed(polars_points)
    if name == "pandas.read_csv (C, chunks)":
        import pandas as pd

        def pandas_points() -> int:
            reader = pd.read_csv(
                path, sep=" ", header=None, names=NAMES, engine="c", chunksize=1 << 20
            )
            return sum(len(frame) for frame in reader)

        return _timed(pandas_points)
    if name == "semantic3d.iter_labels":
        return _timed(lambda: sum(c.size for c in sio.iter_labels(path)))
    if name == "polars.read_csv":
        import polars as pl

        return _timed(lambda: pl.read_csv(path, has_header=False, new_columns=["label"]).height)
    if name == "pandas.read_csv (labels)":
        import pandas as pd

        return _timed(lambda: len(pd.read_csv(path, header=None, engine="c", dtype=np.uint8)))
    if name == "semantic3d.iter_cache":
        return _timed(lambda: sum(c.n_points for c in iter_cache(path)))
    return _run_writer(name, n_points, folder)


def _run_writer(name: str, n_points: int, folder: Path) -> dict[str, float]:
    import semantic3d.io as sio

    out = folder / f"written_{os.getpid()}.txt"
    try:
        if name.startswith("pandas"):
            n_points = min(n_points, PANDAS_WRITE_ROWS)
        cloud = _in_memory(n_points)
        if name == "semantic3d.write_ascii_points":
            return _timed(lambda: sio.write_ascii_points(out, [cloud]))  # type: ignore[list-item]
        if name == "semantic3d.write_labels":
            return _timed(lambda: sio.write_labels(out, [cloud.labels]))  # type: ignore[attr-defined]
        table = _arrow_table(cloud)
        if name == "pyarrow.csv.write_csv":
            return _timed(lambda: _arrow_write(table, out))
        if name == "pyarrow.csv.write_csv (labels)":
            return _timed(lambda: _arrow_write(table.select(["label"]), out))
        frame = table.to_pandas()
        if name == "pandas.to_csv (2 M rows)":
            points = frame[NAMES]
            return _timed(lambda: _pandas_write(points, out, "%.3f"))
        if name == "pandas.to_csv (labels)":
            return _timed(lambda: _pandas_write(frame[["label"]], out, None))
    finally:
        out.unlink(missing_ok=True)
    raise SystemExit(f"unknown contender {name}")


def _arrow_table(cloud: object) -> object:
    import pyarrow as pa

    xyz = cloud.xyz  # type: ignore[attr-defined]
    rgb = cloud.rgb  # type: ignore[attr-defined]
    return pa.table(
        {
            "x": xyz[:, 0],
            "y": xyz[:, 1],
            "z": xyz[:, 2],
            "intensity": cloud.intensity,  # type: ignore[attr-defined]
            "r": rgb[:, 0],
            "g": rgb[:, 1],
            "b": rgb[:, 2],
            "label": cloud.labels,  # type: ignore[attr-defined]
        }
    )


def _arrow_write(table: object, out: Path) -> int:
    import pyarrow.csv as pacsv

    options = pacsv.WriteOptions(include_header=False, delimiter=" ")
    pacsv.write_csv(table, out, options)
    return int(table.num_rows)  # type: ignore[attr-defined]


def _pandas_write(frame: object, out: Path, float_format: str | None) -> int:
    frame.to_csv(out, sep=" ", header=False, index=False, float_format=float_format)  # type: ignore[attr-defined]
    return len(frame)  # type: ignore[arg-type]


# --- parent ---------------------------------------------------------------------------


def measure(name: str, path: Path, n_points: int, folder: Path) -> Run:
    load = os.getloadavg()[0]
    result = subprocess.run(
        [sys.executable, str(HERE), "--child", name, str(path), str(n_points), str(folder)],
        check=True,
        capture_output=True,
        text=True,
    )
    data = json.loads(result.stdout.strip().splitlines()[-1])
    return Run(name=name, load=load, **data)


def measure_all(
    names: list[str], path: Path, n_points: int, folder: Path, repeat: int
) -> list[list[Run]]:
    """``repeat`` rounds, each contender once per round (interleaved, so load drifts evenly)."""
    rounds = [[measure(name, path, n_points, folder) for name in names] for _ in range(repeat)]
    return [list(runs) for runs in zip(*rounds, strict=True)]


_SHORT = {
    "pyarrow.csv.read_csv": "pyarrow",
    "pandas.read_csv (C, chunks)": "pandas",
    "cat (page cache)": "cat",
    "dd O_DIRECT (disk)": "disk",
    "polars.read_csv": "polars",
    "polars.read_csv (points)": "polars",
    "pandas.read_csv (labels)": "pandas",
    "pyarrow.csv.write_csv": "pyarrow",
    "pandas.to_csv (2 M rows)": "pandas",
    "pyarrow.csv.write_csv (labels)": "pyarrow",
    "pandas.to_csv (labels)": "pandas",
    "cat cache columns": "cat",
}


def table(title: str, unit: str, runs: list[list[Run]], references: list[str]) -> str:
    medians = {r[0].name: statistics.median(x.rate for x in r) for r in runs}
    header = f"{'contender':<32} {'M ' + unit + '/s':>9} {'spread':>13} {'ns CPU/' + unit[:-1]:>11}"
    header += "".join(f" {'x ' + _SHORT.get(ref, ref)[:8]:>10}" for ref in references)
    header += f" {'peak RSS MB':>11} {'load':>5}"
    lines = [title, header]
    for r in runs:
        rates = [x.rate / 1e6 for x in r]
        cpu = statistics.median(x.cpu_seconds / x.items * 1e9 for x in r)
        line = f"{r[0].name:<32} {statistics.median(rates):>9.1f} "
        line += f"{min(rates):>6.1f}-{max(rates):<6.1f} {cpu:>11.1f}"
        line += "".join(f" {medians[r[0].name] / medians[ref]:>10.2f}" for ref in references)
        line += (
            f" {max(x.peak_rss_mb for x in r):>11.0f} {statistics.mean(x.load for x in r):>5.1f}"
        )
        lines.append(line)
    return "\n".join(lines)


def make_files(folder: Path, n_points: int) -> tuple[Path, Path]:
    from semantic3d.io import write_ascii_points

    points, labels = folder / f"scan_{n_points}.txt", folder / f"scan_{n_points}.labels"
    write_ascii_points(points, _cloud_chunks(n_points), labels_path=labels)  # type: ignore[arg-type]
    return points, labels


def run_size(n_points: int, folder: Path, repeat: int) -> None:
    free = shutil.disk_usage(folder).free
    needed = n_points * BYTES_PER_POINT * 2  # the files, a cache and a written copy
    if free < needed:
        raise SystemExit(f"{folder}: {free / 1e9:.1f} GB free, {needed / 1e9:.1f} GB needed")
    # Generated in a child: the parent must stay small, its size at fork time is
    # inherited by every child's ru_maxrss.
    points, labels = folder / f"scan_{n_points}.txt", folder / f"scan_{n_points}.labels"
    measure("make files", points, n_points, folder)
    for path in (points, labels):  # into the page cache
        subprocess.run(["cat", str(path)], check=True, stdout=subprocess.DEVNULL)
    print(
        f"\n== {n_points:,} points: {points.stat().st_size / 1e9:.2f} GB of text; "
        f"{os.cpu_count()} cores; load before {os.getloadavg()[0]:.1f}"
    )
    readers = [
        "semantic3d.iter_ascii_points",
        "pyarrow.csv.read_csv",
        "pandas.read_csv (C, chunks)",
        "polars.read_csv (points)",
        "cat (page cache)",
        "dd O_DIRECT (disk)",
    ]
    runs = measure_all(readers, points, n_points, folder, repeat)
    print(
        table(
            "read points",
            "points",
            runs,
            [
                "pyarrow.csv.read_csv",
                "pandas.read_csv (C, chunks)",
                "polars.read_csv (points)",
                "cat (page cache)",
                "dd O_DIRECT (disk)",
            ],
        )
    )
    runs = measure_all(
        ["semantic3d.iter_labels", "polars.read_csv", "pandas.read_csv (labels)"],
        labels,
        n_points,
        folder,
        repeat,
    )
    print(table("read labels", "labels", runs, ["polars.read_csv", "pandas.read_csv (labels)"]))
    writers = ["semantic3d.write_ascii_points", "pyarrow.csv.write_csv", "pandas.to_csv (2 M rows)"]
    runs = measure_all(writers, points, n_points, folder, repeat)
    print(table("write points", "points", runs, writers[1:]))
    writers = [
        "semantic3d.write_labels",
        "pyarrow.csv.write_csv (labels)",
        "pandas.to_csv (labels)",
    ]
    runs = measure_all(writers, labels, n_points, folder, repeat)
    print(table("write labels", "labels", runs, writers[1:]))
    cache = folder / "scan.cache"
    measure("build cache", points, n_points, folder)
    subprocess.run(["sh", "-c", f"cat {cache}/*.npy > /dev/null"], check=True)
    runs = measure_all(
        ["semantic3d.iter_cache", "cat cache columns"], cache, n_points, folder, repeat
    )
    print(table("read the binary cache", "points", runs, ["cat cache columns"]))
    shutil.rmtree(cache)
    points.unlink()
    labels.unlink()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--points", type=int, nargs="+", default=[10_000_000, 50_000_000])
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder")
    parser.add_argument("--child", nargs=4, metavar=("NAME", "PATH", "N_POINTS", "FOLDER"))
    args = parser.parse_args()
    if args.child:
        name, path, n_points, folder = args.child
        print(json.dumps(run_contender(name, Path(path), int(n_points), Path(folder))))
        return
    folder = Path(tempfile.mkdtemp(prefix="bench_io_"))
    try:
        for n_points in args.points:
            run_size(n_points, folder, args.repeat)
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
