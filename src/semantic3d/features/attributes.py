"""Optional appearance features: neighbourhood colour (HSV) and intensity.

Off by default (the benchmark's 3D covariance baseline is geometric). Each pyramid voxel
carries the mean colour and intensity of its points; a query's columns are the HSV of the
mean colour of its neighbours (hue in [0, 1), 0 for greys) and their mean intensity.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import ShapeError
from semantic3d.features.covariance import as_kernel_indices


def compute_attribute_features(
    attributes: NDArray[np.float64],
    neighbours: NDArray[np.integer],
    *,
    colour: bool,
    intensity: bool,
) -> NDArray[np.float32]:
    """Appearance columns of every query: ``hue, saturation, value`` then ``intensity``.

    Args:
        attributes: ``(n, a)`` float64 per-voxel means: ``r g b`` (0..255) first when
            ``colour``, then the intensity when ``intensity``.
        neighbours: ``(m, k)`` integer indices into ``attributes``.
        colour: emit the three HSV columns.
        intensity: emit the intensity column.
    """
    expected = 3 * colour + intensity
    if attributes.ndim != 2 or attributes.shape[1] != expected:
        raise ShapeError(f"attributes: expected (n, {expected}), found {attributes.shape}")
    # One index type and layout for the kernel (each other one is another compilation).
    means = _neighbour_means(
        np.ascontiguousarray(attributes, dtype=np.float64),
        as_kernel_indices(neighbours, attributes.shape[0]),
    )
    columns: list[NDArray[np.float64]] = []
    if colour:
        columns.extend(_rgb_to_hsv(means[:, :3] / 255.0))
    if intensity:
        columns.append(means[:, -1])
    if not columns:
        return np.empty((neighbours.shape[0], 0), np.float32)
    return np.column_stack(columns).astype(np.float32)


def _rgb_to_hsv(rgb: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    high = rgb.max(axis=1)
    low = rgb.min(axis=1)
    spread = high - low
    safe = np.where(spread > 0, spread, 1.0)
    r, g, b = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    hue = np.select(
        [high == r, high == g],
        [((g - b) / safe) % 6.0, (b - r) / safe + 2.0],
        default=(r - g) / safe + 4.0,
    )
    hue = np.where(spread > 0, hue / 6.0, 0.0)
    saturation = np.where(high > 0, spread / np.where(high > 0, high, 1.0), 0.0)
    return [hue, saturation, high]


# Hand-written: a mean over index rows without an (m, k, a) gather temporary.
@numba.njit(cache=True, nogil=True, parallel=True)
def _neighbour_means(
    attributes: NDArray[np.float64], neighbours: NDArray[np.integer]
) -> NDArray[np.float64]:  # pragma: no cover - compiled
    m, k = neighbours.shape
    n_columns = attributes.shape[1]
    out = np.zeros((m, n_columns), np.float64)
    for row in numba.prange(m):
        for j in range(k):
            idx = neighbours[row, j]
            for c in range(n_columns):
                out[row, c] += attributes[idx, c]
        for c in range(n_columns):
            out[row, c] /= k
    return out
