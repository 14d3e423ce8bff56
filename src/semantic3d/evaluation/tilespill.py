"""``TileSpill``: bin streamed points into square XY tiles with a halo, spilling to disk.

Used by the label-agreement check to process two huge scans tile by tile in bounded
memory: each point goes to its *core* tile and, when it lies within ``margin_m`` of a tile
edge, to the *halo* of the neighbouring tiles. A tile's core plus halo then holds every
point within ``margin_m`` of any core point, so nearest-neighbour queries near edges
are exact. Records are buffered in memory up to ``buffer_points`` and then appended to
one file per tile in a temporary folder.
"""

from __future__ import annotations

import tempfile
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType

import numpy as np
from numpy.typing import NDArray

RECORD_COLUMNS = 4
"""A spilled point is one float64 row ``x y z label`` (32 bytes, contiguous: fast to copy
and gather; label values 0..255 are exact in float64)."""

CORE, HALO = 0, 1
TileKey = tuple[int, int]

_NEIGHBOURS = tuple((dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if (dx, dy) != (0, 0))


class TileSpill:
    """Tile-binned point records of several clouds, in memory up to a budget, then on disk.

    Use as a context manager: the spill folder is removed on exit.
    """

    def __init__(
        self,
        *,
        tile_size_m: float,
        margin_m: float,
        buffer_points: int = 1 << 24,
        directory: Path | None = None,
    ) -> None:
        if not tile_size_m > 0:
            raise ValueError(f"tile_size_m: expected a positive size, found {tile_size_m}")
        if not 0 <= margin_m < tile_size_m:
            raise ValueError(
                f"margin_m: expected 0 <= margin < tile size ({tile_size_m}), found {margin_m}"
            )
        self.tile_size_m = float(tile_size_m)
        self.margin_m = float(margin_m)
        self._buffer_points = buffer_points
        self._tmp = tempfile.TemporaryDirectory(prefix="semantic3d-tiles-", dir=directory)
        self._dir = Path(self._tmp.name)
        self._buffers: dict[tuple[int, int, int, int], list[NDArray[np.float64]]] = defaultdict(
            list
        )
        self._buffered = 0
        self._on_disk: set[tuple[int, int, int, int]] = set()
        self._core_tiles: set[TileKey] = set()
        self.spilled_points = 0

    def __enter__(self) -> TileSpill:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Drop the buffers and remove the spill folder."""
        self._buffers.clear()
        self._tmp.cleanup()

    def add(self, cloud: int, xyz: NDArray[np.float64], labels: NDArray[np.uint8]) -> None:
        """Bin the points of cloud number ``cloud`` (core tile + neighbours' halos)."""
        if xyz.shape[0] == 0:
            return
        # Column-wise work throughout: numpy reductions and gathers along axis 0 of an
        # (n, k) array are several times slower than on contiguous 1-D columns or np.take.
        records = np.empty((xyz.shape[0], RECORD_COLUMNS), dtype=np.float64)
        records[:, :3] = xyz
        records[:, 3] = labels
        size, margin = self.tile_size_m, self.margin_m
        x, y = np.ascontiguousarray(xyz[:, 0]), np.ascontiguousarray(xyz[:, 1])
        ix = np.floor(x / size).astype(np.int64)
        iy = np.floor(y / size).astype(np.int64)
        self._add_grouped(cloud, CORE, ix, iy, records)
        if margin == 0:
            return
        # Only points within the margin of an edge (a few percent) go to halos.
        off_x, off_y = x - ix * size, y - iy * size
        low_x, high_x = off_x < margin, off_x >= size - margin
        low_y, high_y = off_y < margin, off_y >= size - margin
        near = np.flatnonzero(low_x | high_x | low_y | high_y)
        if near.size == 0:
            return
        sides = {
            (0, -1): low_x[near],
            (0, 1): high_x[near],
            (1, -1): low_y[near],
            (1, 1): high_y[near],
        }
        ix, iy, records = ix[near], iy[near], np.take(records, near, axis=0)
        for dx, dy in _NEIGHBOURS:
            mask = np.ones(near.size, dtype=bool)
            for axis, d in ((0, dx), (1, dy)):
                if d:
                    mask &= sides[(axis, d)]
            if mask.any():
                chosen = np.flatnonzero(mask)
                self._add_grouped(
                    cloud, HALO, ix[chosen] + dx, iy[chosen] + dy, np.take(records, chosen, axis=0)
                )

    def _add_grouped(
        self,
        cloud: int,
        kind: int,
        ix: NDArray[np.int64],
        iy: NDArray[np.int64],
        records: NDArray[np.float64],
    ) -> None:
        # Group by tile with one sort of a dense tile id: a stable sort of uint16 keys is a
        # radix sort in numpy (linear time), the common case for one chunk.
        x0, y0 = int(ix.min()), int(iy.min())
        nx, ny = int(ix.max()) - x0 + 1, int(iy.max()) - y0 + 1
        dense = (ix - x0) * ny + (iy - y0)
        cells = None
        if nx * ny > max(np.iinfo(np.uint16).max, 4 * ix.shape[0]):
            cells, dense = np.unique(dense, return_inverse=True)  # sparse tiles: renumber
            dense = dense.reshape(-1)
        if int(dense.max()) <= np.iinfo(np.uint16).max:
            dense = dense.astype(np.uint16)
        order = np.argsort(dense, kind="stable")
        counts = np.bincount(dense)
        ends = np.cumsum(counts)
        grouped = np.take(records, order, axis=0)
        for slot in np.flatnonzero(counts).tolist():
            cell = slot if cells is None else int(cells[slot])
            tile = (x0 + cell // ny, y0 + cell % ny)
            begin, end = int(ends[slot] - counts[slot]), int(ends[slot])
            self._buffers[(cloud, kind, *tile)].append(grouped[begin:end])
            if kind == CORE:
                self._core_tiles.add(tile)
        self._buffered += records.shape[0]
        if self._buffered > self._buffer_points:
            self.flush()

    def _path(self, key: tuple[int, int, int, int]) -> Path:
        return self._dir / "{}_{}_{}_{}.bin".format(*key)

    def flush(self) -> None:
        """Append every buffered record to its tile file."""
        for key, parts in self._buffers.items():
            with self._path(key).open("ab") as handle:
                for part in parts:
                    part.tofile(handle)
                    self.spilled_points += part.shape[0]
            self._on_disk.add(key)
        self._buffers.clear()
        self._buffered = 0

    def read(self, cloud: int, kind: int, tile: TileKey) -> NDArray[np.float64]:
        """``(n, 4)`` rows ``x y z label`` of ``cloud`` in the core or halo of ``tile``."""
        key = (cloud, kind, *tile)
        parts: list[NDArray[np.float64]] = []
        if key in self._on_disk:
            flat = np.fromfile(self._path(key), dtype=np.float64)
            parts.append(flat.reshape(-1, RECORD_COLUMNS))
        parts.extend(self._buffers.get(key, []))
        if not parts:
            return np.empty((0, RECORD_COLUMNS), dtype=np.float64)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def tiles(self) -> Iterator[TileKey]:
        """Tiles with core points of any cloud, in a fixed order."""
        yield from sorted(self._core_tiles)

    @property
    def n_tiles(self) -> int:
        """Number of tiles with core points."""
        return len(self._core_tiles)
