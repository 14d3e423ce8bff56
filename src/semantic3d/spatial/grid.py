"""Square XY tiles made of whole cells of an integer grid.

A :class:`TileGrid` cuts the plane into square columns ("tiles") of ``cells_per_tile``
cells of ``cell_size_m``, anchored at ``origin_xy``. A point's tile is computed from its
integer cell (``floor((x - origin) / cell) // cells_per_tile``), exactly as the voxel
pyramid computes its voxels, so every voxel of a grid whose cells nest in the tile's lies
in exactly one tile, however the points are split between processes.

>>> grid = TileGrid(origin_xy=(0.0, 0.0), cell_size_m=0.5, cells_per_tile=20)
>>> grid.tile_size_m
10.0
>>> grid.tile_keys(np.array([[3.0, -0.1, 7.0], [10.0, 19.99, 0.0]])).tolist()
[[0, -1], [1, 1]]
>>> grid.tile_bounds((1, -1))
(10.0, -10.0, 20.0, 0.0)

Inside a tile, :meth:`TileGrid.cell_codes` numbers the squares of a quadtree (the tile cut
into ``2**depth`` by ``2**depth`` squares of whole cells) in Morton order, so that every
square of every level holds a contiguous range of codes; :func:`quadtree_leaves` cuts a
tile's points into squares of at most a given count with them.

>>> grid.cell_codes(np.array([[0.2, 0.2, 0.0], [9.9, 0.2, 0.0], [0.2, 9.9, 0.0]]), depth=1).tolist()
[0, 2, 1]
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import ShapeError

__all__ = [
    "MAX_CELL_DEPTH",
    "Bounds",
    "TileGrid",
    "TileKey",
    "quadtree_leaf_table",
    "quadtree_leaves",
]

TileKey = tuple[int, int]
"""``(ix, iy)`` index of a tile."""

Bounds = tuple[float, float, float, float]
"""``(x_min, y_min, x_max, y_max)`` of a rectangle, metres."""

MAX_CELL_DEPTH = 8
"""Deepest quadtree level :meth:`TileGrid.cell_codes` numbers (its codes are 16-bit)."""


@dataclass(frozen=True, slots=True)
class TileGrid:
    """Square XY tiles of ``cells_per_tile`` cells of ``cell_size_m``, anchored at ``origin_xy``.

    Attributes:
        origin_xy: anchor of cell ``(0, 0)`` (absolute metres).
        cell_size_m: edge of one cell.
        cells_per_tile: cells along a tile's edge.
    """

    origin_xy: tuple[float, float]
    cell_size_m: float
    cells_per_tile: int = 1

    def __post_init__(self) -> None:
        if not (np.isfinite(self.cell_size_m) and self.cell_size_m > 0):
            raise ShapeError(f"cell_size_m: expected a positive size, found {self.cell_size_m}")
        if self.cells_per_tile < 1:
            raise ShapeError(
                f"cells_per_tile: expected a positive count, found {self.cells_per_tile}"
            )
        if not all(np.isfinite(value) for value in self.origin_xy):
            raise ShapeError(f"origin_xy: expected finite values, found {self.origin_xy}")

    @classmethod
    def square(cls, tile_size_m: float, *, origin_xy: tuple[float, float] = (0.0, 0.0)) -> TileGrid:
        """Tiles of ``tile_size_m`` with one cell per tile."""
        return cls(origin_xy=origin_xy, cell_size_m=float(tile_size_m), cells_per_tile=1)

    @property
    def tile_size_m(self) -> float:
        """Edge of a tile."""
        return self.cell_size_m * self.cells_per_tile

    def tile_keys(self, xyz: NDArray[np.float64]) -> NDArray[np.int64]:
        """``(n, 2)`` int64 tile index of each point of ``(n, >=2)`` coordinates (``(0, 0)``
        for a point whose x or y is not a number: :meth:`tile_keys_extent` names it)."""
        from semantic3d.spatial._kernels import tile_keys_extent

        no_marks = np.empty(0, np.bool_)
        keys: NDArray[np.int64] = tile_keys_extent(_coordinates(xyz), *self._numbers(), no_marks)[0]
        return keys

    def tile_keys_extent(
        self, xyz: NDArray[np.float64], *, keep: NDArray[np.bool_] | None = None
    ) -> tuple[NDArray[np.int64], tuple[int, int, int, int] | None]:
        """:meth:`tile_keys` with, in the same pass, ``(x_min, x_max, y_min, y_max)`` of the
        keys of the points ``keep`` marks (all by default; None when it marks none).

        Raises:
            ShapeError: a point's x or y is not a finite number.
        """
        from semantic3d.spatial._kernels import tile_keys_extent

        points = _coordinates(xyz)
        marks = np.empty(0, np.bool_) if keep is None else np.ascontiguousarray(keep, np.bool_)
        if marks.size and marks.shape != (points.shape[0],):
            raise ShapeError(f"keep: expected ({points.shape[0]},), found {marks.shape}")
        keys, bad, x_min, x_max, y_min, y_max = tile_keys_extent(points, *self._numbers(), marks)
        if bad < points.shape[0]:
            raise ShapeError(
                f"xyz: expected finite coordinates, found {points[bad, :2].tolist()} at row {bad}"
            )
        if x_min > x_max:
            return keys, None
        return keys, (int(x_min), int(x_max), int(y_min), int(y_max))

    def cell_codes(self, xyz: NDArray[np.float64], *, depth: int) -> NDArray[np.uint16]:
        """``(n,)`` Morton code of each point's square in its tile, the tile cut into
        ``2**depth`` by ``2**depth`` squares (``0 <= depth <= MAX_CELL_DEPTH``).

        A square is made of whole cells (cell ``c`` of a tile lies in square
        ``c * 2**depth // cells_per_tile``; with fewer cells than squares some squares
        are empty), so every point of a cell, and of a voxel nested in the cells, has
        the same code. The bits of the x square sit above the y square's at every level:
        the squares of level ``d`` are the codes sharing their top ``2 d`` bits.
        """
        from semantic3d.spatial._kernels import tile_cell_codes

        if not 0 <= depth <= MAX_CELL_DEPTH:
            raise ShapeError(f"depth: expected 0..{MAX_CELL_DEPTH}, found {depth}")
        codes: NDArray[np.uint16] = tile_cell_codes(_coordinates(xyz), *self._numbers(), int(depth))
        return codes

    def places(
        self,
        xyz: NDArray[np.float64],
        *,
        depth: int,
        relative_to: NDArray[np.float64],
        out: tuple[NDArray[np.float32], NDArray[np.int64], NDArray[np.uint16]],
    ) -> None:
        """Where each point lies, in one pass: writes into ``out`` its coordinates
        relative to ``relative_to`` rounded to float32 (``(n, 3)``), its packed tile
        (``(n,)``: :meth:`tile_keys`' x shifted 32 bits up plus y) and its square's code
        at ``depth`` (``(n,)``: :meth:`cell_codes`)."""
        from semantic3d.spatial._kernels import tile_places

        if not 0 <= depth <= MAX_CELL_DEPTH:
            raise ShapeError(f"depth: expected 0..{MAX_CELL_DEPTH}, found {depth}")
        points = _coordinates(xyz)
        relative, tiles, codes = out
        n = points.shape[0]
        shapes = (points.shape[1:], relative.shape, tiles.shape, codes.shape)
        dtypes = (relative.dtype, tiles.dtype, codes.dtype)
        if shapes != ((3,), (n, 3), (n,), (n,)) or dtypes != (np.float32, np.int64, np.uint16):
            raise ShapeError(
                f"places: expected (n, 3) points and out float32 (n, 3), int64 (n,), uint16 "
                f"(n,) for n = {n}, found {points.shape}, "
                + ", ".join(f"{a.dtype} {a.shape}" for a in out)
            )
        origin = np.ascontiguousarray(relative_to, dtype=np.float64).reshape(3)
        tile_places(points, *self._numbers(), int(depth), origin, relative, tiles, codes)

    def _numbers(self) -> tuple[float, float, float, int]:
        """The grid as the kernels take it: origin x, origin y, cell size, cells per tile."""
        x0, y0 = self.origin_xy
        return float(x0), float(y0), float(self.cell_size_m), int(self.cells_per_tile)

    def tile_bounds(self, tile: TileKey) -> Bounds:
        """``(x_min, y_min, x_max, y_max)`` of ``tile``."""
        size = self.tile_size_m
        x0, y0 = self.origin_xy
        return (
            x0 + tile[0] * size,
            y0 + tile[1] * size,
            x0 + (tile[0] + 1) * size,
            y0 + (tile[1] + 1) * size,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (see :meth:`from_dict`)."""
        return {
            "origin_xy": list(self.origin_xy),
            "cell_size_m": self.cell_size_m,
            "cells_per_tile": self.cells_per_tile,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TileGrid:
        """The grid :meth:`to_dict` described."""
        x, y = data["origin_xy"]
        return cls(
            origin_xy=(float(x), float(y)),
            cell_size_m=float(data["cell_size_m"]),
            cells_per_tile=int(data["cells_per_tile"]),
        )


def _coordinates(xyz: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(n, >=2)`` coordinates as C-ordered float64 (checked)."""
    points = np.asarray(xyz)
    if points.ndim != 2 or points.shape[1] < 2:
        raise ShapeError(f"xyz: expected (n, >=2) coordinates, found {points.shape}")
    return np.ascontiguousarray(points, dtype=np.float64)


def quadtree_leaves(codes: NDArray[np.integer], *, depth: int, max_count: int) -> NDArray[np.int64]:
    """Cut one tile's points into quadtree squares of at most ``max_count`` points.

    ``codes`` are the points' :meth:`TileGrid.cell_codes` at ``depth``. Starting from the
    whole tile, a square holding more than ``max_count`` points is cut into its four
    quadrants, down to the squares of ``depth`` (which may hold more). Returns, for every
    point, the first code of its leaf square: points share a leaf exactly when they share
    this number. The leaves depend only on the points' codes, not on their order.
    """
    if not 0 <= depth <= MAX_CELL_DEPTH:
        raise ShapeError(f"depth: expected 0..{MAX_CELL_DEPTH}, found {depth}")
    n_codes = 1 << (2 * depth)
    codes = np.asarray(codes)
    if codes.size and (int(codes.min()) < 0 or int(codes.max()) >= n_codes):
        raise ShapeError(f"codes: expected values in 0..{n_codes - 1} for depth {depth}")
    leaf = quadtree_leaf_table(
        np.bincount(codes, minlength=n_codes), depth=depth, max_count=max_count
    )
    leaves: NDArray[np.int64] = leaf[codes]
    return leaves


def quadtree_leaf_table(
    counts: NDArray[np.integer], *, depth: int, max_count: int
) -> NDArray[np.int64]:
    """:func:`quadtree_leaves` from the points per code (``(4**depth,)``): the first code
    of every code's leaf square."""
    if not 0 <= depth <= MAX_CELL_DEPTH:
        raise ShapeError(f"depth: expected 0..{MAX_CELL_DEPTH}, found {depth}")
    if max_count < 1:
        raise ShapeError(f"max_count: expected a positive count, found {max_count}")
    n_codes = 1 << (2 * depth)
    if counts.shape != (n_codes,):
        raise ShapeError(f"counts: expected ({n_codes},) for depth {depth}, found {counts.shape}")
    before = np.zeros(n_codes + 1, np.int64)  # points with a smaller code
    np.cumsum(counts, out=before[1:])
    leaf = np.empty(n_codes, np.int64)
    squares = [(0, n_codes)]  # (first code, codes) of the squares still to place
    while squares:
        first, size = squares.pop()
        if size > 1 and before[first + size] - before[first] > max_count:
            quarter = size // 4
            squares.extend((first + k * quarter, quarter) for k in range(4))
        else:
            leaf[first : first + size] = first
    return leaf
