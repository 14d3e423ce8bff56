"""Prediction tile by tile, for any model that labels one tile of a tile store at a time.

A :class:`TiledModel` says how a scan is cut (:meth:`TiledModel.tile_grid`), whether a
scan has the inputs it needs (:meth:`TiledModel.check_inputs`) and labels one tile
(:meth:`TiledModel.label_tile`, which reads the tile and whatever halo it needs from the
store). :func:`iter_tiled_blocks` is then the whole
:meth:`~semantic3d.baselines.common.prediction.Predictor.iter_labelled_blocks` of such a
model in this process: the streamed scan is spilled once into a temporary tile store
(:mod:`semantic3d.spatial`) and labelled tile by tile, so memory is bounded by a tile and
its halo, whatever the scan's size. :func:`spill_scan` is the part a cluster shares
(:mod:`semantic3d.scale.predict_tiles` labels the tiles on Dask workers with the same
``label_tile``).
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from itertools import chain, islice
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.prediction import LabelledBlock, ScanInputError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.spatial.grid import TileGrid, TileKey
from semantic3d.spatial.store import TemporaryTileStore, TileStore, TileStoreWriter

__all__ = [
    "ScanInputs",
    "TiledModel",
    "iter_tiled_blocks",
    "spill_scan",
]


@dataclass(frozen=True, slots=True)
class ScanInputs:
    """What a streamed scan holds, known once it has been read.

    Attributes:
        n_points: points of the scan.
        has_intensity: some point has a non-zero intensity.
        has_rgb: some point has a non-black colour.
    """

    n_points: int
    has_intensity: bool
    has_rgb: bool


class TiledModel(Protocol):
    """A trained model that labels a scan one tile of a tile store at a time."""

    @property
    def training_scans(self) -> tuple[str, ...]:
        """Names of the scans it was trained on."""
        ...

    @property
    def chunk_size(self) -> int:
        """Points per chunk it wants to read."""
        ...

    def tile_grid(self, first_point: NDArray[np.float64]) -> TileGrid:
        """The tiles of a scan whose first point is ``first_point``."""
        ...

    def check_inputs(self, inputs: ScanInputs) -> None:
        """Raise :class:`ScanInputError` when the scan lacks what the model needs."""
        ...

    def label_tile(
        self, store: TileStore, tile: TileKey
    ) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
        """Scan indices and label values of every point of ``tile``."""
        ...


class _InputsSeen:
    """Counts points and notes non-zero intensities and colours of chunks passing by."""

    def __init__(self) -> None:
        self.n_points = 0
        self.has_intensity = False
        self.has_rgb = False

    def see(self, chunk: PointCloud) -> PointCloud:
        self.n_points += chunk.n_points
        if not self.has_intensity and chunk.n_points:
            self.has_intensity = bool(np.any(chunk.intensity))
        if not self.has_rgb and chunk.n_points:
            self.has_rgb = bool(np.any(chunk.rgb))
        return PointCloud(chunk.xyz, chunk.intensity, chunk.rgb, None)

    def result(self) -> ScanInputs:
        return ScanInputs(self.n_points, self.has_intensity, self.has_rgb)


def spill_scan(
    model: TiledModel, chunks: Iterable[PointCloud], writer_of: _WriterFactory
) -> TileStore:
    """Stream ``chunks`` (labels dropped) into the store ``writer_of(grid)`` writes, then
    check the scan's inputs against the model.

    Raises:
        ScanInputError: the scan has no point, or lacks an input the model needs.
    """
    stream = iter(chunks)
    first = next((c for c in stream if c.n_points), None)
    if first is None:
        raise ScanInputError("expected at least one point, found none")
    grid = model.tile_grid(np.asarray(first.xyz[0], dtype=np.float64))
    seen = _InputsSeen()
    with writer_of(grid) as writer:
        for chunk in chain([first], stream):
            writer.add(seen.see(chunk))
        store = writer.close()
    try:
        model.check_inputs(seen.result())
    except BaseException:
        if store.directory is not None:  # a store made here for this scan
            shutil.rmtree(store.directory, ignore_errors=True)
        raise
    return store


class _WriterFactory(Protocol):
    def __call__(self, grid: TileGrid) -> TileStoreWriter: ...


def iter_tiled_blocks(
    model: TiledModel,
    chunks: Iterable[PointCloud],
    *,
    workdir: Path,
    parallel_tiles: int = 1,
) -> Iterator[LabelledBlock]:
    """Label a streamed scan tile by tile in this process (the ``Predictor`` protocol).

    The tile store lives in memory while it fits the writer's buffer, else under
    ``workdir``; it is removed afterwards. ``parallel_tiles`` > 1 labels that many tiles
    at a time on threads (for a ``label_tile`` that releases the GIL, as torch and numpy
    do): blocks come in completion order, each tile's labels are the same, memory is that
    of the tiles in flight.
    """
    tiles_dir = workdir / "tiles"

    def writer_of(grid: TileGrid) -> TileStoreWriter:
        return TemporaryTileStore.writer(grid=grid, workdir=tiles_dir)

    with TemporaryTileStore.adopt(spill_scan(model, chunks, writer_of)) as store:
        tiled = len(store.tiles) > 1
        if parallel_tiles <= 1 or len(store.tiles) == 1:
            for tile in store.tiles:
                indices, labels = model.label_tile(store, tile)
                yield LabelledBlock(indices, labels, store.n_points, tiled=tiled)
            return
        with ThreadPoolExecutor(parallel_tiles, thread_name_prefix="label-tile") as pool:
            pending: set[Future[tuple[NDArray[np.int64], NDArray[np.uint8]]]] = set()
            tiles = iter(store.tiles)
            try:
                while True:
                    for tile in islice(tiles, parallel_tiles + 1 - len(pending)):
                        pending.add(pool.submit(model.label_tile, store, tile))
                    if not pending:
                        return
                    finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for future in finished:
                        indices, labels = future.result()
                        yield LabelledBlock(indices, labels, store.n_points, tiled=tiled)
            finally:
                for future in pending:
                    future.cancel()
