"""The levels of a sub-cloud: random sampling, and the neighbours every layer gathers from.

RandLA-Net samples points at random between its layers. A sub-cloud is put in a random
order once (a seeded permutation); level ``l + 1`` is then the first
``ceil(n_l / ratio_l)`` points of level ``l``, so every level is a prefix of the one
before and of the sub-cloud. Per level the network needs:

- ``neighbours[l]``: ``(n_l, k)`` the k nearest level-``l`` points of every level-``l``
  point (its local spatial encoding and attentive pooling gather from them). Because
  level ``l + 1`` is a prefix, the first ``n_(l+1)`` rows are also the neighbourhoods that
  pool level ``l``'s features onto level ``l + 1``'s points;
- ``up[l]``: ``(n_l,)`` the nearest level-``l + 1`` point of every level-``l`` point, whose
  features the decoder copies back up.

Sub-clouds of different sizes are stacked into one batch (:func:`stack_levels`): their
points end to end per level and their indices shifted, the way KPConv stacks batches;
nothing is padded. Neighbour searches run where the network runs
(:mod:`~semantic3d.baselines.randla.neighbours`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from semantic3d.baselines.randla.neighbours import knn_cpu, knn_torch
from semantic3d.core.errors import ShapeError, require

torch: Any = require("torch", "torch")

__all__ = ["CloudLevels", "LevelBatch", "build_levels", "level_sizes", "stack_levels"]


def level_sizes(n_points: int, ratios: Sequence[int]) -> tuple[int, ...]:
    """Points of every level of a sub-cloud of ``n_points``: ``n_0 = n_points``, then
    ``n_(l+1) = ceil(n_l / ratios[l])``.

    >>> level_sizes(1000, [4, 4, 2])
    (1000, 250, 63, 32)
    """
    sizes = [int(n_points)]
    for ratio in ratios:
        sizes.append(max(1, math.ceil(sizes[-1] / ratio)))
    return tuple(sizes)


@dataclass(frozen=True, slots=True)
class CloudLevels:
    """The levels of one sub-cloud (its points already in their random order).

    Attributes:
        sizes: points of levels ``0..L``.
        neighbours: per level ``0..L-1``, ``(n_l, k)`` int64 indices into that level.
        up: per level ``0..L-1``, ``(n_l,)`` int64 indices into level ``l + 1``.
    """

    sizes: tuple[int, ...]
    neighbours: tuple[Any, ...]
    up: tuple[Any, ...]


def build_levels(xyz: Any, *, k: int, ratios: Sequence[int], device: Any) -> CloudLevels:
    """The levels of a sub-cloud whose points ``xyz`` are in their random order.

    Args:
        xyz: ``(n, 3)`` float32 local coordinates (an array, or a tensor).
        k: neighbours per point.
        ratios: sampling ratio after each layer.
        device: where the searches run and the indices live: on ``cpu`` the compiled k-d
            tree, elsewhere torch.
    """
    n = int(xyz.shape[0])
    if n == 0:
        raise ShapeError("a sub-cloud of no point: expected at least one")
    sizes = level_sizes(n, ratios)
    neighbours: list[Any] = []
    up: list[Any] = []
    if torch.device(device).type == "cpu":
        points = np.ascontiguousarray(np.asarray(xyz, dtype=np.float32))
        for level in range(len(ratios)):
            here, below = points[: sizes[level]], points[: sizes[level + 1]]
            neighbours.append(torch.from_numpy(knn_cpu(here, here, k)))
            up.append(torch.from_numpy(knn_cpu(below, here, 1)[:, 0].copy()))
    else:
        points_t = torch.as_tensor(xyz, dtype=torch.float32, device=device)
        for level in range(len(ratios)):
            here_t, below_t = points_t[: sizes[level]], points_t[: sizes[level + 1]]
            neighbours.append(knn_torch(here_t, here_t, k))
            up.append(knn_torch(below_t, here_t, 1)[:, 0].contiguous())
    return CloudLevels(sizes, tuple(neighbours), tuple(up))


@dataclass(frozen=True, slots=True)
class LevelBatch:
    """Sub-clouds stacked end to end, level by level, as the network takes them.

    Attributes:
        xyz: per level ``0..L``, ``(N_l, 3)`` float32 coordinates of the stacked points.
        neighbours: per level ``0..L-1``, ``(N_l, k)`` int64 indices into level ``l``.
        pool: per level ``0..L-1``, ``(N_(l+1),)`` int64 rows of ``neighbours[l]`` that
            pool onto level ``l + 1``'s points.
        up: per level ``0..L-1``, ``(N_l,)`` int64 indices into level ``l + 1``.
        cloud_sizes: points of each sub-cloud at level 0.
    """

    xyz: tuple[Any, ...]
    neighbours: tuple[Any, ...]
    pool: tuple[Any, ...]
    up: tuple[Any, ...]
    cloud_sizes: tuple[int, ...]

    @property
    def n_points(self) -> int:
        """Stacked points at level 0."""
        return int(self.xyz[0].shape[0])


def stack_levels(xyz: Sequence[Any], levels: Sequence[CloudLevels], *, device: Any) -> LevelBatch:
    """Stack sub-clouds (``(n_b, 3)`` coordinates and their levels) into one batch on ``device``."""
    if not levels or len(xyz) != len(levels):
        raise ShapeError(
            f"expected one level set per sub-cloud, found {len(xyz)} and {len(levels)}"
        )
    n_levels = len(levels[0].sizes)
    if any(len(cloud.sizes) != n_levels for cloud in levels):
        raise ShapeError("sub-clouds of a batch: expected the same number of levels")
    stacked_xyz = []
    for level in range(n_levels):
        parts = [
            torch.as_tensor(points[: cloud.sizes[level]], dtype=torch.float32).to(device)
            for points, cloud in zip(xyz, levels, strict=True)
        ]
        stacked_xyz.append(torch.cat(parts) if len(parts) > 1 else parts[0])
    neighbours, pool, up = [], [], []
    for level in range(n_levels - 1):
        here = np.cumsum([0] + [cloud.sizes[level] for cloud in levels])
        below = np.cumsum([0] + [cloud.sizes[level + 1] for cloud in levels])
        neighbours.append(
            torch.cat(
                [
                    cloud.neighbours[level].to(device) + int(here[b])
                    for b, cloud in enumerate(levels)
                ]
            )
        )
        up.append(
            torch.cat(
                [cloud.up[level].to(device) + int(below[b]) for b, cloud in enumerate(levels)]
            )
        )
        pool.append(
            torch.cat(
                [
                    torch.arange(cloud.sizes[level + 1], device=device) + int(here[b])
                    for b, cloud in enumerate(levels)
                ]
            )
        )
    return LevelBatch(
        tuple(stacked_xyz),
        tuple(neighbours),
        tuple(pool),
        tuple(up),
        tuple(cloud.sizes[0] for cloud in levels),
    )
