"""The labeller at the paper's scale: a scan of 10**8 points (marked ``slow``).

A synthetic terrestrial scan (dense around its scanner, 1 % far returns, georeferenced
coordinates) is written as a cache. A fresh process opens it for labelling, which builds the
level of detail under 1 GB of peak memory (the issue's goal; its rate, and the times of
the operations below, are measured by ``benchmarks/bench_labelling.py``, not here). This
process then reopens it (the level of detail reused), checks that every point is in exactly
one node and that no node is too large to load (the densest 8-level leaf held 5.1 M points
before the octree grew deeper where points are dense), and runs a polygon split of a 30 m
square around the scanner (its edges cross the dense part), its undo and a plane fit in a
region, each equal to a plain pass over every point (the fit but for points within 10 µm of
its region or tolerance: it tests the level of detail's float32 positions). About 5 GB of
temporary disk; skipped when the disk has less than 12 GB free.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from semantic3d.core.pointcloud import PointCloud
from semantic3d.io.cache import write_cache
from semantic3d.labelling import _op_kernels
from semantic3d.labelling.delta import empty_bits
from semantic3d.labelling.fitting import Region
from semantic3d.labelling.opening import open_label_session
from semantic3d.labelling.session import LabelSession

pytestmark = pytest.mark.slow

N_POINTS = 100_000_000
CHUNK = 1 << 22
STATION = np.array([541_200.0, 4_182_300.0, 52.0])
"""The scanner, in a UTM-like frame: float32 alone would lose centimetres here."""


def _terrestrial_chunks(n_points: int, seed: int = 0) -> Iterator[PointCloud]:
    """Ground and walls within 31 m of the scanner, denser near it; 1 % far returns.

    Drawn straight into their final types and arrays (no int64 colours, no stacked
    copies): 1.6 s per 10 M points here, against 2.6 s drawn as int64 and stacked."""
    rng = np.random.default_rng(seed)
    for start in range(0, n_points, CHUNK):
        size = min(CHUNK, n_points - start)
        distance = rng.random(size)
        np.square(distance, out=distance)
        distance *= 30.0
        distance += 1.0
        far = rng.random(size) < 0.01
        distance[far] = rng.uniform(31.0, 400.0, int(far.sum()))
        angle = rng.uniform(0.0, 2 * np.pi, size)
        xyz = np.empty((size, 3))
        np.multiply(distance, np.cos(angle), out=xyz[:, 0])
        np.multiply(distance, np.sin(angle), out=xyz[:, 1])
        ground = rng.random(size) < 0.6
        xyz[:, 2] = rng.uniform(-1.5, 10.0, size)
        xyz[ground, 2] = rng.normal(-1.5, 0.01, int(ground.sum()))
        xyz += STATION
        yield PointCloud(
            xyz,
            rng.integers(-2000, 2000, size, dtype=np.int32),
            rng.integers(0, 255, (size, 3), dtype=np.uint8),
        )


@pytest.fixture(scope="module")
def large_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("paper-scale")
    if shutil.disk_usage(folder).free < 12e9:
        pytest.skip("a 10**8-point scan needs about 5 GB of temporary disk")
    path = folder / "large.cache"
    write_cache(path, _terrestrial_chunks(N_POINTS))
    return path


_OPEN_IN_A_FRESH_PROCESS = """
import json, resource, sys, time
from semantic3d.labelling.opening import open_label_session
from semantic3d.labelling.session import LabelSession
cache, labels, cache_dir = sys.argv[1:]
started, cpu = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
session = open_label_session(cache, labels_path=labels, cache_dir=cache_dir)
after = resource.getrusage(resource.RUSAGE_SELF)
wall = time.perf_counter() - started
n_nodes = len(session.lod.nodes)
session.close()
peak_kb = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM"))
cpu_s = (after.ru_utime - cpu.ru_utime) + (after.ru_stime - cpu.ru_stime)
print(json.dumps({"wall_s": wall, "cpu_s": cpu_s, "peak_mb": peak_kb / 1024, "nodes": n_nodes}))
"""


def _view_from_above(centre: np.ndarray, half_m: float) -> np.ndarray:
    """A top view whose screen spans ``centre ± half_m`` (row-major view-projection)."""
    scale = 1.0 / half_m
    return np.array(
        [
            [scale, 0, 0, -scale * centre[0]],
            [0, scale, 0, -scale * centre[1]],
            [0, 0, -0.001, 0],
            [0, 0, 0, 1],
        ]
    )


@pytest.fixture(scope="module")
def built(large_scan: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The scan opened for labelling once, in a fresh process: the level of detail built."""
    if not Path("/proc/self/status").exists():
        pytest.skip("the peak memory of a process is read from /proc")
    folder = tmp_path_factory.mktemp("paper-scale-session")
    cache_dir, labels_path = folder / "caches", folder / "large.labels"
    opened = subprocess.run(
        [sys.executable, "-c", _OPEN_IN_A_FRESH_PROCESS, str(large_scan), str(labels_path),
         str(cache_dir)],
        check=True, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    build = json.loads(opened.stdout.strip().splitlines()[-1])
    return {"build": build, "cache_dir": cache_dir}


def _reopen(large_scan: Path, built: dict[str, Any], labels_path: Path) -> LabelSession:
    """A new labelling session of the scan (a new labels file: the whole scan working)."""

    def no_rebuild(stage: str, done: int, total: int) -> None:
        raise AssertionError(f"the level of detail was built again ({stage})")

    return open_label_session(
        large_scan,
        labels_path=labels_path,
        cache_dir=built["cache_dir"],
        progress=no_rebuild,
    )


SQUARE = np.array([[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]])
"""A 30 m square around the scanner in ``_view_from_above(station, 50.0)``."""


def test_a_scan_of_10_to_the_8_points(
    large_scan: Path, built: dict[str, Any], tmp_path: Path
) -> None:
    build = built["build"]  # its rate and the operations' times: benchmarks/bench_labelling.py
    assert build["peak_mb"] < 1024, build  # flat in scan size: a 10**8-point scan is 3 GB
    assert build["nodes"] > 1000, build
    session = _reopen(large_scan, built, tmp_path / "large.labels")
    try:
        lod = session.lod
        assert sum(node.count for node in lod.nodes) == N_POINTS
        # No node too large to load: leaves at most the capacity, coarser nodes about it
        # (5.1 M points in one leaf near the scanner when the octree stopped at 8 levels).
        assert max(node.count for node in lod.nodes if not node.children) <= lod.capacity
        assert max(node.count for node in lod.nodes) <= lod.capacity + 5 * lod.capacity**0.5
        seen = np.zeros(N_POINTS, bool)
        for node in lod.nodes:
            indices = lod.node_indices(node.id)
            assert not seen[indices].any(), node.id
            seen[indices] = True
        assert seen.all()
        del seen

        # A polygon split of a 30 m square around the scanner, its undo.
        local_station = STATION - session.origin
        view = _view_from_above(local_station, 50.0)
        tracemalloc.start()
        session.split(view, SQUARE)
        split_peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        expected = empty_bits(N_POINTS)
        _op_kernels.split_flips(
            np.asarray(session.scan.xyz), 0, session.origin, session.labels,
            np.ones(N_POINTS, bool), np.ones(9, bool), view, SQUARE, True, expected,
        )  # fmt: skip
        np.testing.assert_array_equal(np.packbits(~session.working, bitorder="little"), expected)
        assert 0.3 * N_POINTS < session.working.sum() < 0.95 * N_POINTS
        session.undo()
        assert session.working.all()
        session.redo()
        session.undo()
        assert session.working.all()

        # A plane fit in a 5 m sphere 20 m from the scanner: the ground's points in it.
        centre = local_station + np.array([20.0, 0.0, -1.5])
        seeds = centre + np.array([[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
        plane = {"kind": "plane", "point": centre.tolist(), "normal": [0.0, 0.0, 1.0]}
        region = Region.sphere(centre, 5.0)
        for attempt in range(2):
            preview = session.fit_preview("plane", seeds, tolerance_m=0.05, region=region)
            result = session.fit("plane", seeds, tolerance_m=0.05, region=region, model=plane)
            if attempt == 0:
                session.undo()
        # The float64 reference; a region's nodes are tested from their float32 positions
        # (within 2**-24 of the coordinates), so points within 10 µm of the sphere or of
        # the tolerance may fall either way.
        inliers = undecided = 0
        for start in range(0, N_POINTS, CHUNK):
            xyz = np.asarray(session.scan.xyz[start : start + CHUNK]) - session.origin
            from_centre = np.linalg.norm(xyz - centre, axis=1)
            from_plane = np.abs(xyz[:, 2] - centre[2])
            expected_in = (from_centre <= 5.0) & (from_plane <= 0.05)
            inliers += int(expected_in.sum())
            differ = expected_in != session.working[start : start + CHUNK]
            edge = (np.abs(from_centre - 5.0) < 1e-5) | (np.abs(from_plane - 0.05) < 1e-5)
            assert edge[differ].all(), np.flatnonzero(differ & ~edge)[:10] + start
            undecided += int(differ.sum())
        assert result.n_inliers == int(session.working.sum()) > 100_000
        assert abs(result.n_inliers - inliers) == undecided <= 10
        assert abs(preview.n_inliers - inliers) < 0.02 * inliers  # its own least-squares plane
    finally:
        session.close()
    assert split_peak < 1.3 * N_POINTS + 2_000_000 + 2 * (1 << 16) * 24, split_peak
