"""OccupancyGrid: the 27-voxel test is exact for neighbours within a cell."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from semantic3d.spatial.occupancy import OccupancyGrid


def _clustered(rng: np.random.Generator, n: int) -> np.ndarray:
    centres = rng.uniform(0.0, 4.0, (20, 3))
    return centres[rng.integers(0, 20, n)] + rng.normal(0.0, 0.15, (n, 3))


@pytest.mark.parametrize("max_cells", [1 << 24, 500])
def test_touching_keeps_every_point_with_a_neighbour_within_the_cell(max_cells: int) -> None:
    rng = np.random.default_rng(11)
    source, query = _clustered(rng, 4_000), _clustered(rng, 3_000)
    grid = OccupancyGrid([source, query], cell_m=0.05, max_cells=max_cells)
    assert grid.cell_m >= 0.05 and grid.n_cells <= max(max_cells, 1 << 12)
    touching = grid.touching(grid.mark(grid.keys(source)), grid.keys(query))
    distance, _ = cKDTree(source).query(query, k=1)
    has_neighbour = distance <= 0.05
    assert has_neighbour.any() and (~has_neighbour).any()
    assert touching[has_neighbour].all()  # exact: never drops a point that could match
    assert not touching[distance > 2 * np.sqrt(3) * grid.cell_m].any()  # and filters


def test_keys_stay_inside_the_padded_grid() -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform(-1e3, 1e3, (1_000, 3)) + np.array([870_000.0, 6_500_000.0, 0.0])
    grid = OccupancyGrid([points[:500], points[500:]], cell_m=0.05)
    keys = grid.keys(points)
    assert keys.min() > 0 and keys.max() < grid.n_cells - 1
    assert grid.n_cells <= 8 * 1_000 or grid.n_cells <= 1 << 12


def test_bad_cell() -> None:
    with pytest.raises(ValueError, match="cell_m: expected a positive size, found 0"):
        OccupancyGrid([np.zeros((1, 3))], cell_m=0.0)
