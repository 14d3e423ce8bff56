"""``CovarianceModel``: a fitted classifier with everything needed to reuse it."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.prediction import LabelledBlock
from semantic3d.baselines.covariance.config import ContextConfig, CovarianceConfig
from semantic3d.baselines.covariance.context import (
    GRAPH_CELL_DEPTH,
    label_rows_by_group,
    last_points,
    lists_suffice,
    row_centroids,
)
from semantic3d.baselines.covariance.forest import CompiledClassifier
from semantic3d.core.errors import ShapeError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.core.threads import take_free_threads
from semantic3d.core.timeline import span
from semantic3d.features.multiscale import FeatureTable
from semantic3d.features.pyramid import grid_origin
from semantic3d.spatial.grid import TileGrid

if TYPE_CHECKING:  # the estimator imports scikit-learn; prediction does not need it
    from semantic3d.baselines.covariance.estimator import CovarianceClassifier
    from semantic3d.features.scan import FeatureBlock

logger = logging.getLogger(__name__)

_NO_CONTEXT = ContextConfig(potts_weight=0.0)


@dataclass(frozen=True, slots=True)
class GridSearchResult:
    """Cross-validated scores of every grid point (``GridSearchCV.cv_results_`` essentials).

    Attributes:
        params: the parameter sets, in grid order.
        mean_scores: mean validation score of each set.
        std_scores: standard deviation across folds.
        fit_time_s: mean fit time of each set.
        best_params: the best set.
        best_score: its mean score.
        scoring: the scikit-learn scorer name.
        n_splits: folds (grouped by scan).
    """

    params: tuple[dict[str, Any], ...]
    mean_scores: NDArray[np.float64]
    std_scores: NDArray[np.float64]
    fit_time_s: NDArray[np.float64]
    best_params: dict[str, Any]
    best_score: float
    scoring: str
    n_splits: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (NaN scores as None)."""
        return {
            "scoring": self.scoring,
            "n_splits": self.n_splits,
            "best_params": self.best_params,
            "best_score": _finite(self.best_score),
            "results": [
                {**params, "mean": _finite(mean), "std": _finite(std)}
                for params, mean, std in zip(
                    self.params, self.mean_scores, self.std_scores, strict=True
                )
            ],
        }


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


@dataclass(frozen=True, slots=True)
class CovarianceModel:
    """A trained covariance baseline.

    Attributes:
        classifier: the fitted :class:`CovarianceClassifier` after training; its
            :class:`~semantic3d.baselines.covariance.forest.CompiledClassifier` (no
            scikit-learn object) once saved and loaded. Both predict the same.
        config: the resolved configuration it was trained with.
        feature_names: its input columns, in order.
        training_scans: names of the scans it was trained on.
        n_training_points: sampled training points per label value.
        seed: seed of sampling and forest.
        package_version: semantic3d version that trained it.
        training_time_s: wall time of feature computation plus fitting.
        grid_search: the cross-validation that chose the forest's parameters, when
            training ran one (``config.forest`` then holds the chosen ones).
    """

    classifier: CovarianceClassifier | CompiledClassifier
    config: CovarianceConfig
    feature_names: tuple[str, ...]
    training_scans: tuple[str, ...]
    n_training_points: dict[int, int]
    seed: int
    package_version: str
    training_time_s: float
    grid_search: GridSearchResult | None = None

    @property
    def chunk_size(self) -> int:
        """Points per chunk read while predicting (the configuration's)."""
        return self.config.prediction.chunk_size

    def iter_labelled_blocks(
        self, chunks: Iterable[PointCloud], *, workdir: Path
    ) -> Iterator[LabelledBlock]:
        """Label a streamed scan (the :class:`~semantic3d.baselines.common.Predictor` protocol).

        The scan goes through :func:`~semantic3d.features.scan.map_scan_features` (whole in
        memory when small, tile by tile otherwise: tiles described and labelled on the
        thread budget's threads at once, blocks as they finish; the labels of every tile
        are the same as alone). Each feature row is classified once: in
        voxel mode a row is a level-0 voxel and its label goes to every point inside it
        (they all have the same features, so this *is* per-point prediction); in per-point
        mode every point has its own row.
        """
        from semantic3d.features.scan import map_scan_features

        prediction = self.config.prediction
        positions = _PositionFile(workdir, self.config) if self.context.enabled else None

        def label(block: FeatureBlock) -> LabelledBlock:
            return LabelledBlock(
                block.point_indices,
                self._label_block(block, positions),
                block.n_scan_points,
                tiled=block.tiled,
            )

        yield from map_scan_features(
            chunks if positions is None else positions.record(chunks),
            label,
            config=self.config.features,
            max_points_in_memory=prediction.max_points_in_memory,
            tile_size_m=prediction.tile_size_m,
            workdir=workdir / "tiles",
            # the forest runs on a tile's rows as they are made: its table is never whole
            row_map=self.row_probabilities,
        )

    def _label_block(
        self, block: FeatureBlock, positions: _PositionFile | None
    ) -> NDArray[np.uint8]:
        """Label values of a feature block's points (the rows' labels, per point): from its
        rows' class probabilities where the forest ran as they were made
        (:attr:`~semantic3d.features.multiscale.FeatureTable.mapped`), else from its rows."""
        table = block.table
        graph: dict[str, Any] = {}
        if positions is not None:
            row_xyz = (
                row_centroids(
                    positions.read_xyz(block.point_indices), table.point_row, table.n_rows
                )
                if self.needs_row_positions(table)
                else None  # the graph comes with the features: only the rows' places
            )
            row_tile, row_cell = positions.row_places(
                block.point_indices, table.point_row, table.n_rows
            )
            graph = {
                "row_xyz": row_xyz,
                "row_tile": row_tile,
                "row_cell": row_cell,
                "neighbours": table.neighbours,
            }
        if table.mapped is None:
            row_labels = self.predict_rows(table.values, **graph)
        else:
            row_labels = self.label_probabilities(table.mapped, **graph)
        labels: NDArray[np.uint8] = row_labels[table.point_row]
        return labels

    def needs_row_positions(self, table: FeatureTable) -> bool:
        """Whether :meth:`predict_rows` needs ``row_xyz`` for ``table``: the context step is
        on and the table's neighbour lists are too short for its graph (per-point mode, a
        scan of a few voxels, or ``n_neighbours`` not below the features' k)."""
        return self.context.enabled and not lists_suffice(
            table.neighbours, self.context.n_neighbours
        )

    @property
    def max_parallel_scans(self) -> int:
        """Scans it may label at once on threads of one process
        (:func:`~semantic3d.baselines.common.prediction.parallel_scans_limit`): any number
        where numba's threading layer is thread-safe, else 1."""
        return 64 if concurrent_scans_supported() else 1

    @property
    def context(self) -> ContextConfig:
        """The context step's settings (off for a model saved before it existed)."""
        context: ContextConfig = getattr(self.config, "context", _NO_CONTEXT)
        return context

    @property
    def label_values(self) -> tuple[int, ...]:
        """Label values the classifier can predict."""
        return tuple(int(v) for v in self.classifier.classes_)

    def predict_rows(
        self,
        values: NDArray[np.float32],
        *,
        row_xyz: NDArray[np.floating] | None = None,
        row_tile: NDArray[np.int64] | None = None,
        row_cell: NDArray[np.uint16] | None = None,
        neighbours: NDArray[np.int64] | None = None,
    ) -> NDArray[np.uint8]:
        """Label values of feature rows ``(n, n_features)`` in ``feature_names`` order.

        Without a graph every row gets its most probable class. With the configuration's
        context step on (``[context] potts_weight > 0``) and the rows' nearest neighbours,
        the rows are labelled together by alpha-expansion over their nearest-neighbour
        graph, tile by tile when ``row_tile`` (``(n,)`` tile of each row,
        :func:`point_tiles`) is given, and a tile of more than
        ``[context] max_graph_nodes`` rows in squares of at most that many when
        ``row_cell`` (``(n,)`` square of each row in its tile, :func:`point_cells`) is
        given. The neighbours are ``neighbours``, the feature
        table's lists (:attr:`~semantic3d.features.multiscale.FeatureTable.neighbours`),
        or else found from ``row_xyz`` (``(n, 3)`` position of each row, e.g. the centroid
        of its points).
        """
        if values.ndim != 2 or values.shape[1] != len(self.feature_names):
            raise ShapeError(
                f"feature rows: expected (n, {len(self.feature_names)}), found {values.shape}"
            )
        return self.label_probabilities(
            self.row_probabilities(values),
            row_xyz=row_xyz,
            row_tile=row_tile,
            row_cell=row_cell,
            neighbours=neighbours,
        )

    def row_probabilities(self, values: NDArray[np.float32]) -> NDArray[np.float64]:
        """The forest's class probabilities of feature rows, on the threads a map's last
        tasks find free (a :data:`~semantic3d.features.multiscale.RowMap`)."""
        if values.shape[0] == 0:
            return np.empty((0, len(self.classifier.classes_)), np.float64)
        threads = take_free_threads()  # in a map's last tasks: the threads the others left
        with span("forest", rows=values.shape[0], threads=threads):
            proba: NDArray[np.float64] = self.classifier.compiled_.predict_proba(values)
        return proba

    def label_probabilities(
        self,
        proba: NDArray[np.float64],
        *,
        row_xyz: NDArray[np.floating] | None = None,
        row_tile: NDArray[np.int64] | None = None,
        row_cell: NDArray[np.uint16] | None = None,
        neighbours: NDArray[np.int64] | None = None,
    ) -> NDArray[np.uint8]:
        """Label values of rows from their class probabilities (:meth:`row_probabilities`),
        with the context step as :meth:`predict_rows` has it: ``predict_rows(values, ...)``
        is ``label_probabilities(row_probabilities(values), ...)``."""
        if proba.shape[0] == 0:
            return np.empty(0, np.uint8)
        classes = np.asarray(self.classifier.classes_, dtype=np.uint8)
        context = self.context
        graph = row_xyz is not None or lists_suffice(neighbours, context.n_neighbours)
        if context.enabled and not graph:
            logger.warning("context step skipped: no row positions or neighbours were given")
        if not graph or not context.enabled:
            columns = np.argmax(proba, axis=1)
        else:  # a tile's groups on its task's threads; one group alone on one thread
            with span("cut", rows=proba.shape[0]):
                columns = label_rows_by_group(
                    proba,
                    None if row_xyz is None else np.asarray(row_xyz, dtype=np.float64),
                    np.zeros(proba.shape[0], np.int64) if row_tile is None else row_tile,
                    potts_weight=context.potts_weight,
                    n_neighbours=context.n_neighbours,
                    max_sweeps=context.max_sweeps,
                    neighbours=neighbours,
                    row_cell=row_cell,
                    max_group_rows=context.max_graph_nodes,
                )
        labels: NDArray[np.uint8] = classes[columns]
        return labels


def point_tiles(
    xyz: NDArray[np.float64], *, origin: NDArray[np.float64], config: CovarianceConfig
) -> NDArray[np.int64]:
    """``(n,)`` packed tile of every point on the grid that tiled prediction uses: tiles of
    whole coarsest voxels of about ``[prediction] tile_size_m``, anchored at ``origin``
    (the grid origin of the scan's first point), as in
    :class:`~semantic3d.features.tiling.TiledScan`."""
    keys = _tile_grid(origin, config).tile_keys(xyz)
    packed: NDArray[np.int64] = (keys[:, 0] << 32) + keys[:, 1]
    return packed


def point_cells(
    xyz: NDArray[np.float64], *, origin: NDArray[np.float64], config: CovarianceConfig
) -> NDArray[np.uint16]:
    """``(n,)`` square of every point in its tile (:func:`point_tiles`), the code the
    context step cuts a large tile's graph by
    (:func:`~semantic3d.baselines.covariance.context.label_rows_by_group`)."""
    return _tile_grid(origin, config).cell_codes(xyz, depth=GRAPH_CELL_DEPTH)


def _tile_grid(origin: NDArray[np.float64], config: CovarianceConfig) -> TileGrid:
    features = config.features
    tile_cells = 2 ** (features.n_levels - 1) * max(
        1, math.ceil(config.prediction.tile_size_m / features.coarsest_voxel_size_m - 1e-9)
    )
    return TileGrid(
        origin_xy=(float(origin[0]), float(origin[1])),
        cell_size_m=features.base_voxel_size_m,
        cells_per_tile=tile_cells,
    )


class _PositionFile:
    """The scan's point positions (float32, relative to the grid origin), tiles and
    squares in their tiles kept on disk while it streams, so the context step can place
    the rows of every block in bounded memory."""

    def __init__(self, folder: Path, config: CovarianceConfig) -> None:
        self.folder = folder
        self.config = config
        self._complete = False

    def record(self, chunks: Iterable[PointCloud]) -> Iterator[PointCloud]:
        """Pass ``chunks`` through, appending their positions, tiles and squares to the
        files."""
        self.folder.mkdir(parents=True, exist_ok=True)
        origin: NDArray[np.float64] | None = None
        grid: TileGrid | None = None
        buffers = (np.empty((0, 3), np.float32), np.empty(0, np.int64), np.empty(0, np.uint16))
        with (
            (self.folder / "xyz.f32").open("wb") as xyz_file,
            (self.folder / "tiles.i64").open("wb") as tile_file,
            (self.folder / "cells.u16").open("wb") as cell_file,
        ):
            for chunk in chunks:
                n = chunk.n_points
                if n:
                    if origin is None or grid is None:
                        origin = grid_origin(
                            chunk.xyz[0],
                            coarsest_voxel_size_m=self.config.features.coarsest_voxel_size_m,
                        )
                        grid = _tile_grid(origin, self.config)
                    if n > buffers[1].size:  # the chunks' size: the buffers are reused
                        buffers = (
                            np.empty((n, 3), np.float32),
                            np.empty(n, np.int64),
                            np.empty(n, np.uint16),
                        )
                    # one pass on every thread (positions, tiles and squares of point_tiles
                    # and point_cells), into buffers whose pages are touched once
                    out = (buffers[0][:n], buffers[1][:n], buffers[2][:n])
                    grid.places(chunk.xyz, depth=GRAPH_CELL_DEPTH, relative_to=origin, out=out)
                    xyz_file.write(out[0].data)
                    tile_file.write(out[1].data)
                    cell_file.write(out[2].data)
                yield chunk
        self._complete = True

    def read_xyz(self, point_indices: NDArray[np.int64]) -> NDArray[np.float32]:
        """``(m, 3)`` positions of the given points (of a scan streamed through
        :meth:`record`)."""
        xyz, _, _ = self._open()
        return np.asarray(xyz[point_indices])

    def row_places(
        self, point_indices: NDArray[np.int64], point_row: NDArray[np.int64], n_rows: int
    ) -> tuple[NDArray[np.int64], NDArray[np.uint16]]:
        """``(n_rows,)`` tile and square of every row: those of its last point
        (``point_row`` the row of each of the given points), as numpy's
        ``row_tile[point_row] = tiles`` leaves them. Only each row's last point is read:
        a row is a voxel, so a tile's rows are read, not its points."""
        _, tiles, cells = self._open()
        last = last_points(point_row, n_rows)
        row_tile = np.zeros(n_rows, np.int64)
        row_cell = np.zeros(n_rows, np.uint16)
        placed = last >= 0
        at = np.asarray(point_indices)[last[placed]]
        row_tile[placed] = tiles[at]
        row_cell[placed] = cells[at]
        return row_tile, row_cell

    def _open(self) -> tuple[NDArray[np.float32], NDArray[np.int64], NDArray[np.uint16]]:
        """Maps of the files, new at every call: the pages a block reads leave the
        process's memory with its maps (maps kept would hold every page read, 10 to 22
        bytes a point of the scan, until the end)."""
        if not self._complete:
            raise RuntimeError(f"{self.folder}: read before the scan finished streaming")
        return (
            np.memmap(self.folder / "xyz.f32", dtype=np.float32, mode="r").reshape(-1, 3),
            np.memmap(self.folder / "tiles.i64", dtype=np.int64, mode="r"),
            np.memmap(self.folder / "cells.u16", dtype=np.uint16, mode="r"),
        )


def concurrent_scans_supported() -> bool:
    """Whether scans can be labelled on several threads at once
    (``predict_scans(..., parallel_scans=2)``): the model's compiled kernels are then
    launched from several threads, which numba's ``tbb`` and ``omp`` threading layers
    allow and its ``workqueue`` fallback (no TBB, no OpenMP runtime) does not."""
    _touch_threading_layer(np.zeros(1))
    return str(numba.threading_layer()) != "workqueue"


@numba.njit(cache=True, nogil=True, parallel=True)
def _touch_threading_layer(values: NDArray[np.float64]) -> None:  # pragma: no cover - compiled
    """A parallel kernel's first launch picks numba's threading layer."""
    for index in numba.prange(values.size):
        values[index] = 0.0
