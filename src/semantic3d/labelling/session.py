"""A labelling session: class layers, the working set, operations, undo/redo and save.

The session holds two arrays over the full-resolution scan (in the cache's point order):
``labels`` (uint8, one layer per label value: 0 unlabelled, 1..8 the benchmark's classes)
and ``working`` (the points the next operation acts on). Geometry runs over every working
point, streamed from the cache's ``xyz.npy`` in blocks, never over what the screen shows:

- ``split``: keep the working points inside (or outside) a polygon drawn in a fixed view;
- ``fit``: fit a plane / line / cylinder / sphere through picked points, keep its inliers
  (inside an optional region); ``fit_preview`` shows them first without changing anything;
- ``assign``: move the working points to a class layer (locked layers are never changed);
- ``reset``: the working set becomes every editable point (or every unlabelled one);
- ``move_layer``: move a whole layer to another.

Every operation is a compiled pass (:mod:`~semantic3d.labelling._op_kernels`) writing a
packed :class:`~semantic3d.labelling.delta.Delta`, journalled before it is applied; the
session state is what the journal replays to, so reopening resumes where it stopped.
Operations report progress per block and can be cancelled until they commit
(:mod:`~semantic3d.labelling.progress`).

Memory: two bytes per point (labels, working set), one byte more with a prediction, one
block of coordinates, and per operation two bit masks (1/8 byte per point each) plus the old
label of each point it relabels.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.classes import N_CLASSES
from semantic3d.io.cache import CachedScan
from semantic3d.labelling import _op_kernels as kernels
from semantic3d.labelling import blocks
from semantic3d.labelling.blocks import BLOCK_POINTS
from semantic3d.labelling.delta import Delta, empty_bits
from semantic3d.labelling.errors import OperationError, ReadOnlyError, WholeScanError
from semantic3d.labelling.fitting import Region
from semantic3d.labelling.journal import Journal
from semantic3d.labelling.lod import LodIndex
from semantic3d.labelling.progress import OperationProgress
from semantic3d.labelling.results import (
    MAX_RADIUS_M,
    MAX_SEEDS,
    MAX_TOLERANCE_M,
    OperationResult,
    _layer,
)
from semantic3d.labelling.saving import save_session

__all__ = [
    "BLOCK_POINTS",
    "MAX_RADIUS_M",
    "MAX_SEEDS",
    "MAX_TOLERANCE_M",
    "LabelSession",
    "OperationResult",
]

if TYPE_CHECKING:
    from semantic3d.labelling.fits import FitPreview

logger = logging.getLogger(__name__)

T = TypeVar("T")

N_LAYERS = N_CLASSES + 1


class LabelSession:
    """One scan open for labelling (or viewing, when ``journal`` is ``None``)."""

    def __init__(
        self,
        scan: CachedScan,
        lod: LodIndex,
        labels: NDArray[np.uint8],
        *,
        journal: Journal | None,
        labels_path: Path | None,
        prediction: NDArray[np.uint8] | None = None,
        scan_folder: Path | None = None,
        protected: tuple[Path, ...] = (),
        started_from: Path | None = None,
        working: NDArray[np.bool_] | None = None,
        undo_stack: list[int] | None = None,
        redo_stack: list[int] | None = None,
        hidden: list[bool] | None = None,
        locked: list[bool] | None = None,
    ) -> None:
        self.scan = scan
        self.lod = lod
        self.labels = labels
        self.prediction = prediction
        self.journal = journal
        self.labels_path = labels_path
        self.scan_folder = scan_folder
        self.protected = protected
        self.started_from = started_from
        self.working = np.ones(scan.n_points, bool) if working is None else working
        self.undo_stack = undo_stack or []
        self.redo_stack = redo_stack or []
        self.hidden = np.array(hidden or [False] * N_LAYERS, bool)
        self.locked = np.array(locked or [False] * N_LAYERS, bool)
        self.version = 0
        self.lock = threading.RLock()
        """Serialises operations (held for a whole operation)."""
        self.state_lock = threading.Lock()
        """Held only while the arrays change (node payloads read under it)."""
        self.progress = OperationProgress()
        self._summary: tuple[int, dict[str, Any]] | None = None

    # -- properties ---------------------------------------------------------------------------

    @property
    def read_only(self) -> bool:
        return self.journal is None

    @property
    def n_points(self) -> int:
        return self.scan.n_points

    @property
    def origin(self) -> NDArray[np.float64]:
        return self.lod.origin

    def editable_layers(self) -> NDArray[np.bool_]:
        """Per label value: the layer is neither hidden nor locked."""
        return ~(self.hidden | self.locked)

    def editable(self) -> NDArray[np.bool_]:
        """Points in a layer that is neither hidden nor locked."""
        return self.editable_layers()[self.labels]

    def summary(self) -> dict[str, Any]:
        """Counts per layer, the working set, undo/redo availability (cached per version)."""
        if self._summary is not None and self._summary[0] == self.version:
            return self._summary[1]
        counts = np.zeros(N_LAYERS, np.int64)
        kernels.layer_counts(self.labels, counts)
        summary = {
            "n_points": self.n_points,
            "read_only": self.read_only,
            "version": self.version,
            "layers": [
                {
                    "value": value,
                    "count": int(counts[value]),
                    "hidden": bool(self.hidden[value]),
                    "locked": bool(self.locked[value]),
                }
                for value in range(N_LAYERS)
            ],
            "n_working": int(np.count_nonzero(self.working)),
            "can_undo": bool(self.undo_stack),
            "can_redo": bool(self.redo_stack),
            "labels_path": None if self.labels_path is None else str(self.labels_path),
            "started_from": None if self.started_from is None else str(self.started_from),
            "has_prediction": self.prediction is not None,
        }
        self._summary = (self.version, summary)
        return summary

    # -- node payloads ------------------------------------------------------------------------

    def node_points(self, node_id: int) -> bytes:
        """Static part of a node: float32 positions, then rgb, then intensity (uint8)."""
        points = self.lod.read_node(node_id)
        return points.positions.tobytes() + points.rgb.tobytes() + points.intensity.tobytes()

    def node_state(self, node_id: int) -> bytes:
        """Live part of a node: class, working flag, prediction (255 = none), one byte each."""
        indices = self.lod.node_indices(node_id)
        prediction = (
            np.full(indices.size, 255, np.uint8)
            if self.prediction is None
            else self.prediction[indices]
        )
        with self.state_lock:
            return (
                self.labels[indices].tobytes()
                + self.working[indices].astype(np.uint8).tobytes()
                + prediction.tobytes()
            )

    # -- streaming ----------------------------------------------------------------------------

    def iter_blocks(self, *, active_only: bool = True) -> Iterator[tuple[int, NDArray[np.float64]]]:
        """``(first index, float64 xyz block)`` over the scan in order (:func:`.blocks.iter_blocks`)."""
        return blocks.iter_blocks(self, active_only=active_only)

    def map_blocks(
        self,
        work: Callable[[int, NDArray[np.float64]], T],
        *,
        active_only: bool = True,
        threads: int | None = None,
    ) -> list[T | None]:
        """``work`` on every block of the scan, on threads (:func:`.blocks.map_blocks`)."""
        return blocks.map_blocks(self, work, active_only=active_only, threads=threads)

    def _run(self, name: str) -> _Running:
        self._require_writable()
        return _Running(self, name)

    def _require_writable(self) -> Journal:
        if self.journal is None:
            raise ReadOnlyError("this scan is open read-only (semantic3d view): nothing changes")
        return self.journal

    def _commit(self, operation: dict[str, Any], delta: Delta, **extra: Any) -> OperationResult:
        """Journal ``delta`` (durable before it shows), then apply it."""
        journal = self._require_writable()
        self.progress.committing()
        entry_id = journal.append_apply(operation, delta)
        with self.state_lock:
            delta.apply(self.labels, self.working)
            self.undo_stack.append(entry_id)
            self.redo_stack.clear()
            self.version += 1
        return OperationResult(
            operation["name"],
            entry_id,
            int(np.count_nonzero(self.working)),
            delta.n_changed,
            delta.n_flipped,
            **extra,
        )

    # -- operations ---------------------------------------------------------------------------

    def split(
        self, view_projection: ArrayLike, polygon: ArrayLike, *, keep: str = "inside"
    ) -> OperationResult:
        """Keep the working points inside (``keep="inside"``) or outside a screen polygon.

        See :func:`semantic3d.labelling.selections.split`.
        """
        from semantic3d.labelling import selections

        return selections.split(self, view_projection, polygon, keep=keep)

    def split_mask(
        self,
        view_projection: ArrayLike,
        mask: NDArray[np.uint8],
        *,
        width: int,
        height: int,
        keep: str = "inside",
    ) -> OperationResult:
        """Keep the working points inside (or outside) a screen mask (a lasso, a brush stroke).

        See :func:`semantic3d.labelling.selections.split_mask`.
        """
        from semantic3d.labelling import selections

        return selections.split_mask(
            self, view_projection, mask, width=width, height=height, keep=keep
        )

    def fit_preview(
        self,
        kind: str,
        seeds: ArrayLike,
        *,
        tolerance_m: float,
        radius_m: float | None = None,
        region: Region | None = None,
    ) -> FitPreview:
        """Fit a model through ``seeds`` and count its inliers in ``region``; change nothing.

        See :func:`semantic3d.labelling.fits.fit_preview`.
        """
        from semantic3d.labelling import fits

        return fits.fit_preview(
            self, kind, seeds, tolerance_m=tolerance_m, radius_m=radius_m, region=region
        )

    def fit(
        self,
        kind: str,
        seeds: ArrayLike,
        *,
        tolerance_m: float,
        radius_m: float | None = None,
        region: Region | None = None,
        model: dict[str, Any] | None = None,
    ) -> OperationResult:
        """Fit a model through ``seeds``; the working set keeps its inliers in ``region``.

        See :func:`semantic3d.labelling.fits.fit`.
        """
        from semantic3d.labelling import fits

        return fits.fit(
            self,
            kind,
            seeds,
            tolerance_m=tolerance_m,
            radius_m=radius_m,
            region=region,
            model=model,
        )

    def assign(self, value: int, *, confirm_whole_scan: bool = False) -> OperationResult:
        """Move the editable working points to the layer of label value ``value``.

        When the working set holds every editable point (the whole scan, as when a
        session starts), :class:`WholeScanError` is raised unless ``confirm_whole_scan``.
        """
        value = _layer(value)
        with self.lock, self._run("assign"):
            if self.locked[value]:
                raise OperationError(f"layer {value} is locked: unlock it to add points")
            editable = self.editable_layers()
            n_editable, n_chosen = kernels.count_active(self.labels, self.working, editable)
            if not confirm_whole_scan and n_chosen and n_chosen == n_editable:
                raise WholeScanError(
                    f"the working set is the whole scan ({n_chosen:,} editable points): "
                    f"confirm to assign every one of them to layer {value}"
                )
            changed = empty_bits(self.n_points)
            n = kernels.assign_marks(self.labels, self.working, editable, value, changed)
            old = np.empty(n, np.uint8)
            kernels.gather_marked(self.labels, changed, old)
            delta = Delta(self.n_points, changed, old, None, value, empty_bits(self.n_points))
            return self._commit({"name": "assign", "value": value}, delta)

    def reset(self, *, scope: str = "all") -> OperationResult:
        """The working set becomes every editable point (``scope="unlabelled"``: label 0 only)."""
        if scope not in ("all", "unlabelled"):
            raise OperationError(f"scope: expected 'all' or 'unlabelled', found {scope!r}")
        with self.lock, self._run("reset"):
            flip = empty_bits(self.n_points)
            kernels.reset_flips(
                self.labels, self.working, self.editable_layers(), scope == "unlabelled", flip
            )
            delta = Delta.working_only(self.n_points, flip)
            return self._commit({"name": "reset", "scope": scope}, delta)

    def move_layer(self, source: int, target: int) -> OperationResult:
        """Move every point of layer ``source`` to layer ``target``."""
        source, target = _layer(source), _layer(target)
        with self.lock, self._run("move layer"):
            for value in (source, target):
                if self.locked[value]:
                    raise OperationError(f"layer {value} is locked: unlock it to move points")
            changed = empty_bits(self.n_points)
            n = 0 if source == target else kernels.layer_marks(self.labels, source, changed)
            old = np.full(n, source, np.uint8)
            delta = Delta(self.n_points, changed, old, None, target, empty_bits(self.n_points))
            operation = {"name": "move_layer", "source": source, "target": target}
            return self._commit(operation, delta)

    def set_layer(
        self, value: int, *, hidden: bool | None = None, locked: bool | None = None
    ) -> None:
        """Hide / lock a layer (a setting: kept in the journal, not in the undo history)."""
        value = _layer(value)
        with self.lock:
            if hidden is not None:
                self.hidden[value] = hidden
            if locked is not None:
                self.locked[value] = locked
            if self.journal is not None:
                self.journal.set_meta(hidden=self.hidden.tolist(), locked=self.locked.tolist())
            self.version += 1

    def _step(self, kind: str) -> OperationResult:
        with self.lock, self._run(kind):
            journal = self._require_writable()
            stack = self.undo_stack if kind == "undo" else self.redo_stack
            if not stack:
                raise OperationError(f"nothing to {kind}")
            target = stack[-1]
            delta = journal.delta(target)
            self.progress.committing()
            entry = journal.append_step(kind, target)
            with self.state_lock:
                if kind == "undo":
                    delta.revert(self.labels, self.working)
                    self.redo_stack.append(self.undo_stack.pop())
                else:
                    delta.apply(self.labels, self.working)
                    self.undo_stack.append(self.redo_stack.pop())
                self.version += 1
            return OperationResult(
                kind, entry, int(np.count_nonzero(self.working)), delta.n_changed, delta.n_flipped
            )

    def undo(self) -> OperationResult:
        """Revert the last operation still applied."""
        return self._step("undo")

    def redo(self) -> OperationResult:
        """Reapply the last undone operation."""
        return self._step("redo")

    def cancel(self) -> bool:
        """Ask the running operation to stop (``False`` when none can be stopped)."""
        return self.progress.cancel()

    def save(self, path: str | Path | None = None, *, overwrite: bool = False) -> Path:
        """Write the labels as a ``.labels`` file, atomically; return its path.

        ``path`` ``None`` writes the session's labels file; another name must pass
        :func:`~semantic3d.labelling.saving.check_save_target`. The journal records the
        save before the rename (see :func:`~semantic3d.labelling.saving.save_session`).
        """
        with self.lock:
            journal = self._require_writable()
            if self.labels_path is None:
                raise OperationError("save: expected a path to write the labels to, found none")
            return save_session(
                journal,
                self.labels,
                self.working,
                labels_path=self.labels_path,
                requested=path,
                scan_folder=self.scan_folder,
                protected=self.protected,
                overwrite=overwrite,
                block_points=BLOCK_POINTS,
            )

    def close(self) -> None:
        """Close the journal (every committed operation is kept) and the level of detail."""
        if self.journal is not None:
            self.journal.close()
        self.lod.close()


class _Running:
    """``with``: the session's progress shows the operation ``name`` until it ends."""

    def __init__(self, session: LabelSession, name: str) -> None:
        self.session = session
        self.name = name

    def __enter__(self) -> None:
        self.session.progress.start(self.name, self.session.n_points)

    def __exit__(self, *exc: object) -> None:
        self.session.progress.finish()
