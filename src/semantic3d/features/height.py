"""Height features of a neighbourhood (Hackel et al. 2016, table 1).

For a query at height ``z`` whose neighbours span ``z_min..z_max``:
``vertical_range = z_max - z_min``, ``height_below = z - z_min``,
``height_above = z_max - z`` (columns of :data:`~semantic3d.features.names.HEIGHT_FEATURES`).
A query need not be one of its neighbours (per-point mode), so ``height_below`` and
``height_above`` may be negative.

The compiled kernel, :func:`~semantic3d.features.covariance.height_kernel`, lives beside
the covariance kernel: the fused per-level ``geometry_kernel`` inlines the same row
function, so the height columns of the multi-scale features are exactly these.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import ShapeError
from semantic3d.features.covariance import as_kernel_indices, height_kernel
from semantic3d.features.names import HEIGHT_FEATURES

N_HEIGHT_COLUMNS = len(HEIGHT_FEATURES)

__all__ = ["N_HEIGHT_COLUMNS", "compute_height_features", "height_kernel"]


def compute_height_features(
    points: NDArray[np.float64],
    neighbours: NDArray[np.integer],
    queries: NDArray[np.float64],
) -> NDArray[np.float32]:
    """``(m, 3)`` float32 height features of every query (see the module docstring).

    Args:
        points: ``(n, 3)`` float64 candidate neighbours.
        neighbours: ``(m, k)`` integer indices into ``points``.
        queries: ``(m, 3)`` float64 query points.
    """
    if (
        neighbours.ndim != 2
        or neighbours.shape[1] < 1
        or queries.shape
        != (
            neighbours.shape[0],
            3,
        )
    ):
        raise ShapeError(
            f"neighbours/queries: expected (m, k) and (m, 3), found "
            f"{neighbours.shape} and {queries.shape}"
        )
    indices = as_kernel_indices(neighbours, points.shape[0])
    out = np.empty((indices.shape[0], N_HEIGHT_COLUMNS), np.float32)
    height_kernel(
        np.ascontiguousarray(points, dtype=np.float64),
        indices,
        np.ascontiguousarray(queries, dtype=np.float64),
        out,
    )
    return out
