"""A small simulated scan shared by the labelling tests (built once per test session)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from semantic3d.datasets.simulator import simulate
from semantic3d.io import build_cache, read_labels
from semantic3d.io.cache import CachedScan

NODE_CAPACITY = 3000


@dataclass(frozen=True)
class SimulatedScan:
    points_path: Path
    truth_path: Path
    cache: CachedScan
    truth: np.ndarray
    station_m: tuple[float, float, float]


@pytest.fixture(scope="session")
def simulated_scan(tmp_path_factory: pytest.TempPathFactory) -> SimulatedScan:
    out = tmp_path_factory.mktemp("simulated")
    result = simulate("village", out=out, n_points=40_000, seed=3)
    scan = result.scans[0]
    cache = build_cache(scan.points_path, out / "scan.cache")
    return SimulatedScan(
        scan.points_path,
        scan.labels_path,
        cache,
        read_labels(scan.labels_path),
        tuple(scan.station.position),
    )
