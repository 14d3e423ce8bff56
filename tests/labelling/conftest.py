"""A small simulated scan shared by the labelling tests (built once per test session)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from semantic3d.datasets.simulator import simulate
from semantic3d.io import build_cache, read_labels
from semantic3d.io.cache import CachedScan
from semantic3d.labelling.cachedir import CACHE_DIR_ENV

NODE_CAPACITY = 3000
PORT = 8765
"""The port TestClient requests name in their Host header (nothing listens there)."""


@pytest.fixture(scope="session")
def labelling_cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("user-cache")


@pytest.fixture(autouse=True)
def _cache_dir(labelling_cache_dir: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Caches of every labelling test go to one temporary folder, never to ~/.cache."""
    monkeypatch.setenv(CACHE_DIR_ENV, str(labelling_cache_dir))
    return labelling_cache_dir


def api_client(app):  # type: ignore[no-untyped-def]
    """A TestClient speaking to ``app`` as the page does: loopback Host, the launch's secret."""
    from fastapi.testclient import TestClient

    from semantic3d.labelling.security import TOKEN_HEADER

    return TestClient(
        app,
        base_url=f"http://127.0.0.1:{PORT}",
        headers={TOKEN_HEADER: app.state.secret},
    )


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
