"""A labelling session: class layers, the working set, operations, undo/redo and save.

The session holds two arrays over the full-resolution scan (in the cache's point order):
``labels`` (uint8, one layer per label value: 0 unlabelled, 1..8 the benchmark's classes)
and ``working`` (the points the next operation acts on). Geometry runs over every working
point, streamed from the cache's ``xyz.npy`` in blocks, never over what the screen shows:

- ``split``: keep the working points inside (or outside) a polygon drawn in a fixed view;
- ``fit``: fit a plane / line / cylinder / sphere near picked points, keep its inliers;
- ``assign``: move the working points to a class layer (locked layers are never changed);
- ``reset``: the working set becomes every editable point (or every unlabelled one);
- ``move_layer``: move a whole layer to another.

Every operation is one entry of the :class:`~semantic3d.labelling.journal.Journal`; the
session state is what the journal replays to, so reopening resumes where it stopped.
Memory: two bytes per point (labels and working set) plus one block of coordinates.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.classes import N_CLASSES
from semantic3d.io.cache import CachedScan
from semantic3d.labelling import geometry
from semantic3d.labelling.errors import OperationError, ReadOnlyError, WholeScanError
from semantic3d.labelling.journal import Delta, Journal
from semantic3d.labelling.lod import LodIndex
from semantic3d.labelling.saving import check_save_target, file_identity, write_labels_staged

__all__ = ["BLOCK_POINTS", "MAX_RADIUS_M", "MAX_TOLERANCE_M", "LabelSession", "OperationResult"]

logger = logging.getLogger(__name__)

BLOCK_POINTS = 1 << 20
"""Points read at a time when an operation streams the scan's coordinates."""

N_LAYERS = N_CLASSES + 1
_CANDIDATES_MAX = 200_000
MAX_TOLERANCE_M = 100.0
"""Largest fit tolerance accepted (metres)."""
MAX_RADIUS_M = 100_000.0
"""Largest candidate radius of a fit accepted (metres)."""
MAX_SEEDS = 1000


@dataclass(frozen=True, slots=True)
class OperationResult:
    """What an operation did."""

    operation: str
    entry_id: int | None
    n_working: int
    n_changed_labels: int
    n_working_changed: int
    model: dict[str, Any] | None = None
    n_inliers: int | None = None
    rms_m: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "operation": self.operation,
            "entry_id": self.entry_id,
            "n_working": self.n_working,
            "n_changed_labels": self.n_changed_labels,
            "n_working_changed": self.n_working_changed,
            "model": self.model,
            "n_inliers": self.n_inliers,
            "rms_m": None if self.rms_m is None or not math.isfinite(self.rms_m) else self.rms_m,
        }


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

    def editable(self) -> NDArray[np.bool_]:
        """Points in a layer that is neither hidden nor locked."""
        return ~(self.hidden | self.locked)[self.labels]

    def summary(self) -> dict[str, Any]:
        """Counts per layer, the working set, undo/redo availability."""
        counts = np.bincount(self.labels, minlength=N_LAYERS)
        return {
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
            "n_working": int(self.working.sum()),
            "can_undo": bool(self.undo_stack),
            "can_redo": bool(self.redo_stack),
            "labels_path": None if self.labels_path is None else str(self.labels_path),
            "started_from": None if self.started_from is None else str(self.started_from),
            "has_prediction": self.prediction is not None,
        }

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
        with self.lock:
            return (
                self.labels[indices].tobytes()
                + self.working[indices].astype(np.uint8).tobytes()
                + prediction.tobytes()
            )

    # -- streaming geometry -------------------------------------------------------------------

    def _iter_working(
        self, mask: NDArray[np.bool_]
    ) -> Iterator[tuple[NDArray[np.int64], NDArray[np.float64]]]:
        """(indices, re-centred float64 coordinates) of the points of ``mask``, in blocks."""
        path = self.scan.path / "xyz.npy"
        offset = int(self.scan.xyz.offset) if isinstance(self.scan.xyz, np.memmap) else 128
        buffer = np.empty((BLOCK_POINTS, 3), np.float64)
        with path.open("rb", buffering=0) as stream:
            for start in range(0, self.n_points, BLOCK_POINTS):
                stop = min(start + BLOCK_POINTS, self.n_points)
                selected = np.flatnonzero(mask[start:stop])
                if selected.size == 0:
                    continue
                block = buffer[: stop - start]
                stream.seek(offset + start * 24)
                stream.readinto(block.data.cast("B"))
                block -= self.origin  # the buffer is ours: re-centre in place
                if selected.size == block.shape[0]:
                    yield selected + start, block
                else:
                    yield selected + start, block[selected]

    def _sample_near(
        self, mask: NDArray[np.bool_], centre: NDArray[np.float64], radius: float
    ) -> NDArray[np.float64]:
        """A uniform sample (at most ``_CANDIDATES_MAX``) of the points of ``mask`` near ``centre``.

        Each near point draws a random key and the smallest keys are kept, block by block:
        memory stays at one block plus the sample however many points are near.
        """
        rng = np.random.default_rng(0)
        kept = np.empty((0, 3))
        keys = np.empty(0)
        for _, xyz in self._iter_working(mask):
            offset = xyz - centre
            near = xyz[np.einsum("ij,ij->i", offset, offset) <= radius * radius]
            kept = np.concatenate([kept, near])
            keys = np.concatenate([keys, rng.random(len(near))])
            if len(kept) > _CANDIDATES_MAX:
                best = np.argpartition(keys, _CANDIDATES_MAX)[:_CANDIDATES_MAX]
                kept, keys = kept[best], keys[best]
        return kept

    def _require_writable(self) -> Journal:
        if self.journal is None:
            raise ReadOnlyError("this scan is open read-only (semantic3d view): nothing changes")
        return self.journal

    def _commit(
        self,
        operation: dict[str, Any],
        labels: NDArray[np.uint8],
        working: NDArray[np.bool_],
        **extra: Any,
    ) -> OperationResult:
        """Journal the change from the current state to (labels, working), then adopt it."""
        journal = self._require_writable()
        delta = Delta.between(self.labels, labels, self.working, working)
        entry_id = journal.append_apply(operation, delta)  # durable before it shows
        delta.apply(self.labels, self.working)
        self.undo_stack.append(entry_id)
        self.redo_stack.clear()
        self.version += 1
        return OperationResult(
            operation["name"],
            entry_id,
            int(self.working.sum()),
            int(delta.changed.size),
            int(delta.working_flip.size),
            **extra,
        )

    # -- operations ---------------------------------------------------------------------------

    def split(
        self, view_projection: ArrayLike, polygon: ArrayLike, *, keep: str = "inside"
    ) -> OperationResult:
        """Keep the working points inside (``keep="inside"``) or outside a screen polygon."""
        if keep not in ("inside", "outside"):
            raise OperationError(f"keep: expected 'inside' or 'outside', found {keep!r}")
        matrix = np.asarray(view_projection, np.float64)
        vertices = np.asarray(polygon, np.float64)
        with self.lock:
            self._require_writable()
            active = self.working & self.editable()
            new_working = self.working.copy()
            for indices, xyz in self._iter_working(active):
                inside = geometry.select_in_polygon(xyz, matrix, vertices)
                new_working[indices] = inside if keep == "inside" else ~inside
            operation = {
                "name": "split",
                "keep": keep,
                "view_projection": matrix.reshape(-1).tolist(),
                "polygon": vertices.tolist(),
            }
            return self._commit(operation, self.labels, new_working)

    def fit(
        self,
        kind: str,
        seeds: ArrayLike,
        *,
        tolerance_m: float,
        radius_m: float | None = None,
    ) -> OperationResult:
        """Fit a model near ``seeds`` (re-centred metres); the working set keeps its inliers.

        Candidates are the working points within ``radius_m`` of the seeds' centre (by
        default 1.5 × the seeds' spread, at least 1 m); the fitted model then selects its
        inliers among all working points of the scan.
        """
        try:
            model_kind = geometry.ModelKind(kind)
        except ValueError:
            known = ", ".join(k.value for k in geometry.ModelKind)
            raise OperationError(f"kind: expected one of {known}, found {kind!r}") from None
        try:
            seed_xyz = np.asarray(seeds, np.float64).reshape(-1, 3)
        except (TypeError, ValueError):
            raise OperationError("seeds: expected a list of [x, y, z] points") from None
        if not 1 <= len(seed_xyz) <= MAX_SEEDS:
            raise OperationError(
                f"seeds: expected 1 to {MAX_SEEDS} picked points, found {len(seed_xyz)}"
            )
        if not np.isfinite(seed_xyz).all():
            raise OperationError("seeds: expected finite coordinates, found NaN or infinity")
        _check_distance("tolerance_m", tolerance_m, MAX_TOLERANCE_M)
        if radius_m is not None:
            _check_distance("radius_m", radius_m, MAX_RADIUS_M)
        centre = seed_xyz.mean(axis=0)
        spread = float(np.linalg.norm(seed_xyz - centre, axis=1).max())
        radius = float(radius_m) if radius_m is not None else max(1.5 * spread, 1.0)
        with self.lock:
            self._require_writable()
            active = self.working & self.editable()
            candidates = self._sample_near(active, centre, radius)
            try:
                fitted = geometry.fit_model(
                    model_kind, candidates, tolerance_m=tolerance_m, seeds=seed_xyz
                )
            except ValueError as exc:
                raise OperationError(f"fit {model_kind.value}: {exc}") from None
            new_working = self.working.copy()
            for indices, xyz in self._iter_working(active):
                new_working[indices] = fitted.model.distance(xyz) <= tolerance_m
            operation = {
                "name": "fit",
                "kind": model_kind.value,
                "seeds": seed_xyz.tolist(),
                "tolerance_m": tolerance_m,
                "radius_m": radius,
                "model": fitted.model.to_dict(),
            }
            return self._commit(
                operation,
                self.labels,
                new_working,
                model=fitted.model.to_dict(),
                n_inliers=int(new_working.sum()),
                rms_m=fitted.rms_m,
            )

    def assign(self, value: int, *, confirm_whole_scan: bool = False) -> OperationResult:
        """Move the editable working points to the layer of label value ``value``.

        When the working set holds every editable point (the whole scan, as when a
        session starts), :class:`WholeScanError` is raised unless ``confirm_whole_scan``.
        """
        value = _layer(value)
        with self.lock:
            self._require_writable()
            if self.locked[value]:
                raise OperationError(f"layer {value} is locked: unlock it to add points")
            editable = self.editable()
            chosen = self.working & editable
            if not confirm_whole_scan and chosen.any() and not (editable & ~self.working).any():
                raise WholeScanError(
                    f"the working set is the whole scan ({int(chosen.sum()):,} editable "
                    f"points): confirm to assign every one of them to layer {value}"
                )
            labels = self.labels.copy()
            labels[chosen] = value
            return self._commit({"name": "assign", "value": value}, labels, self.working)

    def reset(self, *, scope: str = "all") -> OperationResult:
        """The working set becomes every editable point (``scope="unlabelled"``: label 0 only)."""
        if scope not in ("all", "unlabelled"):
            raise OperationError(f"scope: expected 'all' or 'unlabelled', found {scope!r}")
        with self.lock:
            self._require_writable()
            working = self.editable()
            if scope == "unlabelled":
                working &= self.labels == 0
            return self._commit({"name": "reset", "scope": scope}, self.labels, working)

    def move_layer(self, source: int, target: int) -> OperationResult:
        """Move every point of layer ``source`` to layer ``target``."""
        source, target = _layer(source), _layer(target)
        with self.lock:
            self._require_writable()
            for value in (source, target):
                if self.locked[value]:
                    raise OperationError(f"layer {value} is locked: unlock it to move points")
            labels = self.labels.copy()
            labels[self.labels == source] = target
            operation = {"name": "move_layer", "source": source, "target": target}
            return self._commit(operation, labels, self.working)

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

    def undo(self) -> OperationResult:
        """Revert the last operation still applied."""
        with self.lock:
            journal = self._require_writable()
            if not self.undo_stack:
                raise OperationError("nothing to undo")
            target = self.undo_stack[-1]
            delta = journal.delta(target)
            entry = journal.append_step("undo", target)
            delta.revert(self.labels, self.working)
            self.redo_stack.append(self.undo_stack.pop())
            self.version += 1
            return OperationResult(
                "undo", entry, int(self.working.sum()), delta.changed.size, delta.working_flip.size
            )

    def redo(self) -> OperationResult:
        """Reapply the last undone operation."""
        with self.lock:
            journal = self._require_writable()
            if not self.redo_stack:
                raise OperationError("nothing to redo")
            target = self.redo_stack[-1]
            delta = journal.delta(target)
            entry = journal.append_step("redo", target)
            delta.apply(self.labels, self.working)
            self.undo_stack.append(self.redo_stack.pop())
            self.version += 1
            return OperationResult(
                "redo", entry, int(self.working.sum()), delta.changed.size, delta.working_flip.size
            )

    def save(self, path: str | Path | None = None, *, overwrite: bool = False) -> Path:
        """Write the labels as a ``.labels`` file, atomically; return its path.

        ``path`` ``None`` writes the session's labels file; another name must pass
        :func:`~semantic3d.labelling.saving.check_save_target` (a ``*.labels`` file in the
        labels file's or the scan's folder, not one the session reads, an existing one only
        with ``overwrite``). The journal records the save before the rename (see
        :mod:`~semantic3d.labelling.saving`).
        """
        with self.lock:
            journal = self._require_writable()
            if self.labels_path is None:
                raise OperationError("save: expected a path to write the labels to, found none")
            target = check_save_target(
                path,
                labels_path=self.labels_path,
                scan_folder=self.scan_folder,
                protected=self.protected,
                overwrite=overwrite,
            )
            editing = target == self.labels_path
            labels = self.labels.copy()
            working = self.working.copy()

            def record(sha256: str) -> None:
                meta = {"pending_sha256": sha256} if editing else None
                journal.append_checkpoint(labels, working, note=f"saved {target.name}", meta=meta)

            sha256 = write_labels_staged(
                target, labels, before_rename=record, block_points=BLOCK_POINTS
            )
            if editing:
                journal.set_meta(
                    saved_identity=file_identity(target), saved_sha256=sha256, pending_sha256=None
                )
            return target

    def close(self) -> None:
        """Close the journal (every committed operation is kept)."""
        if self.journal is not None:
            self.journal.close()


def _check_distance(name: str, value: float, maximum: float) -> None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(value, bool) or not (math.isfinite(number) and 0 < number <= maximum):
        raise OperationError(
            f"{name}: expected a finite distance in metres, 0 < {name} <= {maximum:g}, "
            f"found {value!r}"
        )


def _layer(value: int) -> int:
    if isinstance(value, bool) or int(value) != value or not 0 <= int(value) <= N_CLASSES:
        raise OperationError(f"layer: expected a label value in 0..{N_CLASSES}, found {value!r}")
    return int(value)
