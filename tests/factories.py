"""Small generated data for tests: seeded clouds and hypothesis strategies."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

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


GEO_ORIGIN = np.array([870_000.0, 6_617_000.0, 0.0])
"""Lambert-93 coordinates like the IGN sample's: millimetres must survive at this size."""

ROUND_TRIP = settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@st.composite
def clouds(
    draw: st.DrawFn, *, max_points: int = 40, millimetres: bool = False, labels: bool | None = None
) -> PointCloud:
    """Random clouds: empty or small, near 0 or georeferenced, signed intensities, labels 0..8.

    With ``millimetres`` the coordinates are whole millimetres (what LAS stores exactly
    and the benchmark's files hold); otherwise any float64.
    """
    n = draw(st.integers(0, max_points))
    origin = GEO_ORIGIN if draw(st.booleans()) else np.zeros(3)
    if millimetres:
        mm = draw(arrays(np.int64, (n, 3), elements=st.integers(-(10**8), 10**8)))
        xyz = np.round(origin + mm / 1000.0, 3)
    else:
        offsets = draw(arrays(np.float64, (n, 3), elements=st.floats(-1e5, 1e5, allow_nan=False)))
        xyz = origin + offsets
    intensity = draw(
        arrays(np.int32, n, elements=st.integers(np.iinfo(np.int32).min, np.iinfo(np.int32).max))
    )
    rgb = draw(arrays(np.uint8, (n, 3)))
    with_labels = draw(st.booleans()) if labels is None else labels
    label_values = draw(arrays(np.uint8, n, elements=st.integers(0, 8))) if with_labels else None
    return PointCloud.from_arrays(xyz, intensity=intensity, rgb=rgb, labels=label_values)


def split(cloud: PointCloud) -> list[PointCloud]:
    """``cloud`` cut into uneven chunks, one of them empty, as a streaming writer may get them."""
    n = cloud.n_points
    cuts = [0, n // 3, n // 3, 2 * n // 3, n]
    return [cloud[a:b] for a, b in pairwise(cuts)]
