"""k nearest neighbours of a sub-cloud's points: the compiled k-d tree on the CPU, torch on a GPU.

On the CPU the search is the project's compiled k-d tree (:class:`~semantic3d.spatial.kdtree.KdTree`,
the one :mod:`semantic3d.features` uses: exact, built and searched on numba's threads
without the GIL, float32 coordinates relative to the sub-cloud's centre, equal distances
ordered by index). On a
GPU it is a brute-force search in torch, a block of queries at a time: every distance
computed on the device and the ``k`` smallest kept (``torch.topk``), which is what a GPU
does well for the block sizes a network pass holds (tens to hundreds of thousands of
points). Both return, per query, the indices of the ``k`` nearest points sorted by
distance; when fewer than ``k`` points exist, the farthest one found repeats.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import ShapeError, require

__all__ = ["knn_cpu", "knn_torch"]

_TORCH_BLOCK_ENTRIES = 1 << 25
"""Distances computed at once by :func:`knn_torch` (128 MiB of float32)."""


def knn_cpu(points: NDArray[np.float32], queries: NDArray[np.float32], k: int) -> NDArray[np.int64]:
    """``(m, k)`` int64 indices of the ``k`` nearest ``points`` of every query, nearest first.

    Args:
        points: ``(n, 3)`` float32 points searched (n >= 1).
        queries: ``(m, 3)`` float32 query points.
        k: neighbours per query (repeated from the last one found when ``n < k``).
    """
    from semantic3d.spatial.kdtree import KdTree

    points = _checked(points, "points")
    queries = _checked(queries, "queries")
    n = points.shape[0]
    if n == 0:
        raise ShapeError("k-NN search among no points: expected at least one")
    k_eff = min(k, n)
    if queries.shape[0] == 0:
        return np.empty((0, k), np.int64)
    found, _ = KdTree(points).query(queries, k=k_eff)
    indices = found.astype(np.int64)
    return _padded(indices, k)


def knn_torch(points: Any, queries: Any, k: int) -> Any:
    """:func:`knn_cpu` in torch, on the tensors' device: ``(m, k)`` int64 indices.

    Args:
        points: ``(n, 3)`` float tensor (n >= 1).
        queries: ``(m, 3)`` float tensor on the same device.
        k: neighbours per query (repeated from the last one found when ``n < k``).
    """
    torch: Any = require("torch", "torch")
    n = int(points.shape[0])
    if points.ndim != 2 or points.shape[1] != 3 or queries.ndim != 2 or queries.shape[1] != 3:
        raise ShapeError(
            f"points/queries: expected (n, 3) and (m, 3), found {tuple(points.shape)} and "
            f"{tuple(queries.shape)}"
        )
    if n == 0:
        raise ShapeError("k-NN search among no points: expected at least one")
    k_eff = min(k, n)
    m = int(queries.shape[0])
    out = torch.empty((m, k_eff), dtype=torch.int64, device=queries.device)
    points = points.float()
    squared = (points * points).sum(dim=1)
    step = max(1, _TORCH_BLOCK_ENTRIES // n)
    for begin in range(0, m, step):
        block = queries[begin : begin + step].float()
        # |q - p|^2 = |q|^2 - 2 q.p + |p|^2: one matrix product per block
        distances = (block * block).sum(dim=1, keepdim=True) - 2.0 * block @ points.T + squared
        out[begin : begin + step] = torch.topk(distances, k_eff, dim=1, largest=False).indices
    if k_eff < k:
        out = torch.cat([out, out[:, -1:].expand(m, k - k_eff)], dim=1)
    return out


def _checked(array: NDArray[Any], name: str) -> NDArray[np.float32]:
    array = np.ascontiguousarray(array, dtype=np.float32)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ShapeError(f"{name}: expected (n, 3), found {array.shape}")
    return array


def _padded(indices: NDArray[np.int64], k: int) -> NDArray[np.int64]:
    if indices.shape[1] >= k:
        return indices
    extra = np.repeat(indices[:, -1:], k - indices.shape[1], axis=1)
    return np.concatenate([indices, extra], axis=1)
