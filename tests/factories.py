"""Small generated data for tests."""

from __future__ import annotations

import numpy as np

from semantic3d.core import PointCloud


def random_cloud(n: int, *, seed: int = 0, labels: bool = True, offset: float = 0.0) -> PointCloud:
    """A reproducible cloud with millimetre coordinates, signed intensities and labels 0..8."""
    rng = np.random.default_rng(seed)
    xyz = np.round(rng.uniform(-50.0, 50.0, (n, 3)) + offset, 3)
    return PointCloud.from_arrays(
        xyz,
        intensity=rng.integers(-2048, 2048, n),
        rgb=rng.integers(0, 256, (n, 3)),
        labels=rng.integers(0, 9, n) if labels else None,
    )
