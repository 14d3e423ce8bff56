"""Opening a scan for labelling or viewing: caches, which labels are read, where saves go.

A scan's ``NAME.labels`` is usually its ground truth, so a labelling session never writes
over a labels file it did not write itself unless told to (``overwrite``):

- the labels it **starts from** are read once, read-only (``start_from``; by default
  the scan's own ``NAME.labels`` when there is one);
- it **writes** one labels file (``labels_path``), which must not exist, or must be the
  output of an earlier session (its journal ``NAME.labels.journal`` beside it records the
  file as it is now: that session is resumed with its undo history), or ``overwrite``
  must be given (the file is then edited in place, starting from its own labels).

:func:`plan_labels` is the command's default: ``NAME.labels`` when the scan has none yet
(or when an earlier session wrote it), else ``NAME.edit.labels`` beside the scan, starting
from ``NAME.labels``; a scan folder that cannot be written asks for ``--labels``.

Caches (the scan's binary cache, the level-of-detail index) go to the cache folder of
:mod:`~semantic3d.labelling.cachedir`, never beside the scan.
"""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import numpy as np

from semantic3d.core.errors import OutputExistsError
from semantic3d.labelling.cachedir import entry_name, resolve_cache_dir
from semantic3d.labelling.errors import OperationError
from semantic3d.labelling.journal import Journal
from semantic3d.labelling.labelfile import build_cache_if_needed, read_label_file
from semantic3d.labelling.lod import LOD_VERSION, open_lod
from semantic3d.labelling.saving import (
    LABELS_SUFFIX,
    file_identity,
    file_sha256,
    journal_matches_file,
)
from semantic3d.labelling.session import LabelSession

__all__ = [
    "LabelsOutput",
    "LabelsPlan",
    "journal_path_for",
    "labels_output_state",
    "open_label_session",
    "plan_labels",
    "scan_id",
]

logger = logging.getLogger(__name__)

EDIT_SUFFIX = ".edit.labels"


class LabelsOutput(StrEnum):
    """What a labels file is to a session that would write it."""

    ABSENT = "absent"
    """No such file: a session creates it (or resumes an unsaved journal)."""
    OURS = "ours"
    """Written by an earlier session whose journal records it as it is: resumed."""
    FOREIGN = "foreign"
    """Any other existing file (a ground truth, a prediction): written only when told."""


def journal_path_for(labels_path: Path) -> Path:
    """Where the journal of a ``.labels`` file lives: beside it, ``NAME.labels.journal``."""
    return labels_path.with_name(labels_path.name + ".journal")


def scan_id(cache_path: Path) -> str:
    """A short identity of a cached scan (its meta.json), recorded in journals."""
    import hashlib

    return hashlib.sha256((cache_path / "meta.json").read_bytes()).hexdigest()[:16]


def labels_output_state(labels_path: Path) -> LabelsOutput:
    """Whether ``labels_path`` is absent, an earlier session's output, or someone else's."""
    journal = journal_path_for(labels_path)
    meta = Journal.read_meta(journal) if journal.is_file() else None
    if meta is not None and journal_matches_file(meta, labels_path)[0]:
        return LabelsOutput.OURS if labels_path.exists() else LabelsOutput.ABSENT
    return LabelsOutput.FOREIGN if labels_path.exists() else LabelsOutput.ABSENT


def default_labels_path(scan_path: Path) -> Path:
    """The scan's own labels: ``NAME.labels`` beside ``NAME.txt`` (or the cache folder)."""
    return scan_path.with_suffix(LABELS_SUFFIX)


@dataclass(frozen=True, slots=True)
class LabelsPlan:
    """Which labels a labelling session reads and where it writes."""

    output: Path
    start_from: Path | None
    state: LabelsOutput
    overwrite: bool

    def describe(self) -> str:
        """One line for the command to print before it starts."""
        if self.state is LabelsOutput.OURS:
            return f"resuming {self.output} (its journal holds the undo history)"
        if self.state is LabelsOutput.FOREIGN:
            return f"editing {self.output} in place (--overwrite)"
        source = (
            f"starting from {self.start_from} (read-only)"
            if self.start_from is not None
            else "starting unlabelled"
        )
        return f"{source}; saving to {self.output}"


def plan_labels(
    scan_path: str | Path,
    *,
    labels: str | Path | None = None,
    start_from: str | Path | None = None,
    overwrite: bool = False,
) -> LabelsPlan:
    """Decide the labels file a ``label`` command writes and the labels it starts from.

    Raises:
        OutputExistsError: ``labels`` exists, was not written by a labelling session, and
            ``overwrite`` was not given; or both default names are taken.
        OperationError: the scan's folder cannot be written and no ``labels`` was given;
            ``start_from`` does not exist.
    """
    scan = Path(scan_path)
    own = default_labels_path(scan)
    source = Path(start_from) if start_from is not None else None
    if source is not None and not source.is_file():
        raise OperationError(f"{source}: expected a .labels file to start from, found none")
    if labels is not None:
        output = Path(labels)
        if output.suffix != LABELS_SUFFIX:
            raise OperationError(
                f"--labels: expected a file name ending in {LABELS_SUFFIX}, found {output.name!r}"
            )
    else:
        folder = own.parent if str(own.parent) else Path()
        if not os.access(folder, os.W_OK):
            raise OperationError(
                f"{folder}: the scan's folder is not writable; pass --labels OUT.labels "
                "(a file in a folder you can write)"
            )
        if labels_output_state(own) is not LabelsOutput.FOREIGN:
            output = own
        else:
            output = own.with_name(own.name[: -len(LABELS_SUFFIX)] + EDIT_SUFFIX)
            if labels_output_state(output) is LabelsOutput.FOREIGN and not overwrite:
                raise OutputExistsError(
                    f"{output}: already exists and no labelling journal beside it records it; "
                    "pass --labels OUT.labels, or --overwrite to edit it in place"
                )
    state = labels_output_state(output)
    if state is LabelsOutput.FOREIGN and not overwrite:
        raise OutputExistsError(
            f"{output}: already exists and was not written by a labelling session (it may be "
            "a scan's ground truth); pass --overwrite to edit it in place, or another --labels"
        )
    if source is None and own.is_file() and own.resolve() != output.resolve():
        source = own
    return LabelsPlan(output, source, state, overwrite)


def _move_aside(journal: Path) -> Path:
    stale = journal.with_name(f"{journal.name}.stale-{uuid.uuid4().hex[:8]}")
    journal.rename(stale)
    for suffix in ("-wal", "-shm"):
        side = journal.with_name(journal.name + suffix)
        if side.exists():
            side.rename(stale.with_name(stale.name + suffix))
    return stale


def open_label_session(
    scan_path: str | Path,
    *,
    labels_path: str | Path | None = None,
    start_from: str | Path | None = None,
    prediction_path: str | Path | None = None,
    read_only: bool = False,
    overwrite: bool = False,
    cache_dir: str | Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    node_capacity: int | None = None,
) -> LabelSession:
    """Open ``scan_path`` (any point format or a cache folder) for labelling or viewing.

    Viewing (``read_only``) reads ``labels_path`` and ``prediction_path`` and writes
    nothing but caches. Labelling writes ``labels_path`` only (see the module's rules):
    an earlier session's output is resumed from its journal; a missing file starts from
    ``start_from`` (read-only) or unlabelled; any other existing file raises
    :class:`OutputExistsError` unless ``overwrite`` (it is then edited, starting from its
    own labels). Every labels file read is checked first (:class:`LabelFileError`).
    Caches go to ``cache_dir`` (default: :func:`~semantic3d.labelling.cachedir.default_cache_dir`).
    """
    folder = resolve_cache_dir(cache_dir)
    scan = build_cache_if_needed(scan_path, cache_dir=folder, progress=progress)
    lod_kwargs = {} if node_capacity is None else {"capacity": node_capacity}
    lod = open_lod(
        scan.path,
        directory=folder / f"{entry_name(scan.path)}.lod-v{LOD_VERSION}",
        progress=progress,
        **lod_kwargs,
    )
    for version in range(1, LOD_VERSION):  # an older format's index, replaced by this one
        shutil.rmtree(folder / f"{entry_name(scan.path)}.lod-v{version}", ignore_errors=True)
    labels_file = None if labels_path is None else Path(labels_path)
    source = None if start_from is None else Path(start_from)
    prediction = (
        None
        if prediction_path is None
        else read_label_file(Path(prediction_path), n_points=scan.n_points)
    )
    scan_folder = Path(scan_path).resolve().parent
    if read_only:
        labels = (
            read_label_file(labels_file, n_points=scan.n_points)
            if labels_file is not None
            else np.zeros(scan.n_points, np.uint8)
        )
        return LabelSession(
            scan,
            lod,
            labels,
            journal=None,
            labels_path=labels_file,
            prediction=prediction,
            scan_folder=scan_folder,
        )
    if labels_file is None:
        raise OperationError("labelling needs a labels file to save to (--labels)")
    if labels_file.suffix != LABELS_SUFFIX:
        raise OperationError(
            f"labels_path: expected a file name ending in {LABELS_SUFFIX}, found {labels_file.name!r}"
        )
    if source is not None and not source.is_file():
        raise OperationError(f"{source}: expected a .labels file to start from, found none")
    protected = tuple(
        p
        for p in (source, None if prediction_path is None else Path(prediction_path))
        if p is not None
    )
    ground_truth = default_labels_path(Path(scan_path))
    if ground_truth.is_file() and ground_truth.resolve() != labels_file.resolve():
        protected = (*protected, ground_truth)
    common = {
        "labels_path": labels_file,
        "prediction": prediction,
        "scan_folder": scan_folder,
        "protected": protected,
    }
    identity = scan_id(scan.path)
    journal_file = journal_path_for(labels_file)
    meta = Journal.read_meta(journal_file) if journal_file.is_file() else None
    matches, by_content = (
        (False, False) if meta is None else journal_matches_file(meta, labels_file)
    )
    if matches:
        journal = Journal(journal_file, scan_id=identity, n_points=scan.n_points)
        state = journal.replay()
        if state is not None:
            if by_content:  # killed after the save's rename, before its last record
                journal.set_meta(
                    saved_identity=file_identity(labels_file),
                    saved_sha256=file_sha256(labels_file),
                    pending_sha256=None,
                )
            logger.info("%s: resuming %d journal entries", journal_file, state.n_entries)
            meta = journal.meta()
            return LabelSession(
                scan,
                lod,
                state.labels,
                journal=journal,
                working=state.working,
                undo_stack=state.undo_stack,
                redo_stack=state.redo_stack,
                hidden=meta.get("hidden"),
                locked=meta.get("locked"),
                started_from=None if meta.get("start_from") is None else Path(meta["start_from"]),
                **common,  # type: ignore[arg-type]
            )
        journal.close()
    if labels_file.exists() and not overwrite:
        raise OutputExistsError(
            f"{labels_file}: already exists and was not written by a labelling session (it "
            "may be a scan's ground truth); pass overwrite (--overwrite) to edit it in place, "
            "or choose another labels file"
        )
    if journal_file.exists():
        stale = _move_aside(journal_file)
        logger.warning("%s: does not describe %s; moved to %s", journal_file, labels_file, stale)
    initial = labels_file if labels_file.exists() else source
    labels = (
        read_label_file(initial, n_points=scan.n_points)
        if initial is not None
        else np.zeros(scan.n_points, np.uint8)
    )
    labels_file.parent.mkdir(parents=True, exist_ok=True)
    journal = Journal(journal_file, scan_id=identity, n_points=scan.n_points)
    journal.append_checkpoint(
        labels,
        np.ones(scan.n_points, bool),
        note="opened",
        meta={
            "saved_identity": file_identity(labels_file),
            "saved_sha256": None,
            "pending_sha256": None,
            "start_from": None if initial is None else str(initial),
        },
    )
    return LabelSession(
        scan,
        lod,
        labels,
        journal=journal,
        started_from=initial,
        **common,  # type: ignore[arg-type]
    )
