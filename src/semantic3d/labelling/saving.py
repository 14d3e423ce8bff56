"""Where a labelling session may write, and how a save stays in step with the journal.

**Targets.** A session writes its own labels file (chosen when it opened). A save to
another name (``POST /api/save {"path": ...}``) is accepted only for a ``*.labels`` name in
the labels file's folder or the scan's folder (a relative name is taken in the labels
file's folder; ``..`` and symbolic links are resolved before the check), never over the
labels the session started from or the prediction it shows, and over another existing
file only with ``overwrite``.

**Saves and the journal.** A save writes the labels under a temporary name, fsyncs it,
then records in the journal, in one transaction, the state it holds (a checkpoint) and
the SHA-256 of the file's bytes (``pending_sha256``), and only then renames the file into
place. After the rename it records the file's identity (size, modification time). A
process killed between the rename and that last record leaves a file whose identity the
journal does not know but whose content hash it does: reopening compares contents and
resumes with the whole undo history (:func:`journal_matches_file`).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import OutputExistsError
from semantic3d.io.staging import StagedPath
from semantic3d.labelling.errors import OperationError

__all__ = [
    "LABELS_SUFFIX",
    "check_save_target",
    "file_identity",
    "file_sha256",
    "journal_matches_file",
    "save_session",
    "write_labels_staged",
]

LABELS_SUFFIX = ".labels"
_BLOCK = 1 << 22


def file_identity(path: Path) -> list[int] | None:
    """``[size, mtime_ns]`` of ``path``, ``None`` when it does not exist."""
    if not path.is_file():
        return None
    stat = path.stat()
    return [int(stat.st_size), int(stat.st_mtime_ns)]


def file_sha256(path: Path) -> str:
    """The SHA-256 of the bytes of ``path``."""
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        while block := stream.read(_BLOCK):
            digest.update(block)
    return digest.hexdigest()


def journal_matches_file(meta: dict[str, Any], path: Path) -> tuple[bool, bool]:
    """Whether the journal whose ``meta`` is given describes ``path`` as it is now.

    Returns ``(matches, by_content)``: the file has the identity the journal last
    recorded (``saved_identity``; ``base_identity`` in older journals), or, failing that,
    its bytes hash to the last saved or the pending save's SHA-256 (``by_content``: the
    caller records the new identity).
    """
    identity = file_identity(path)
    expected = meta.get("saved_identity", meta.get("base_identity"))
    if identity == expected:
        return True, False
    if identity is None:
        return False, False
    hashes = {meta.get("saved_sha256"), meta.get("pending_sha256")} - {None}
    if hashes and file_sha256(path) in hashes:
        return True, True
    return False, False


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def check_save_target(
    requested: str | Path | None,
    *,
    labels_path: Path,
    scan_folder: Path | None,
    protected: tuple[Path, ...],
    overwrite: bool,
) -> Path:
    """The file a save may write for ``requested`` (``None``: the session's labels file).

    Raises:
        OperationError: not a ``*.labels`` name, outside the labels file's and the scan's
            folders, or one of the ``protected`` files (the labels the session started
            from, the prediction it shows).
        OutputExistsError: another existing file without ``overwrite``.
    """
    own = labels_path.resolve()
    if requested is None or str(requested) == "":
        return labels_path
    raw = Path(requested).expanduser()
    candidate = (raw if raw.is_absolute() else labels_path.parent / raw).resolve()
    if candidate == own:
        return labels_path
    if candidate.suffix != LABELS_SUFFIX or candidate.name.startswith("."):
        raise OperationError(
            f"save: expected a file name ending in {LABELS_SUFFIX} (not hidden), found {raw.name!r}"
        )
    roots = [labels_path.parent.resolve()]
    if scan_folder is not None:
        roots.append(scan_folder.resolve())
    if not any(_inside(candidate.parent, root) for root in roots):
        where = " or ".join(str(root) for root in roots)
        raise OperationError(f"save: expected a .labels file under {where}, found {candidate}")
    if any(candidate == p.resolve() for p in protected):
        raise OperationError(
            f"save: {candidate.name} is what this session reads (the labels it started from "
            "or the prediction it shows); choose another name"
        )
    if not candidate.parent.is_dir():
        raise OperationError(f"save: expected an existing folder, found none at {candidate.parent}")
    exists = candidate.exists() or candidate.is_symlink()
    scan = _scan_beside(candidate)
    if exists and scan is not None:
        raise OperationError(
            f"save: {candidate.name} holds the labels of the scan {scan.name} beside it "
            "(its ground truth); choose another name"
        )
    if exists and not overwrite:
        raise OutputExistsError(
            f"{candidate}: already exists and is not the file being edited; "
            "pass overwrite to replace it"
        )
    return candidate


_SCAN_SUFFIXES = (".txt", ".las", ".laz", ".ply", ".cache")


def _scan_beside(labels: Path) -> Path | None:
    """The scan ``NAME.txt`` (``.las``, ``.laz``, ``.ply``, ``.cache``) beside ``NAME.labels``."""
    for suffix in _SCAN_SUFFIXES:
        scan = labels.with_suffix(suffix)
        if scan.exists():
            return scan
    return None


def _fsync_folder(folder: Path) -> None:
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def write_labels_staged(
    path: Path,
    labels: NDArray[np.uint8],
    *,
    before_rename: Any = None,
    block_points: int = 1 << 20,
) -> str:
    """Write ``labels`` to ``path`` (staged, fsynced, renamed); return the file's SHA-256.

    ``before_rename(sha256)`` runs once the temporary file is complete and durable, right
    before the rename: the journal records the save there. On any exception (Ctrl-C
    included) the temporary file is removed and ``path`` is left as it was.
    """
    from semantic3d.io.labels import format_labels_bytes

    staged = StagedPath(path)
    digest = hashlib.sha256()
    try:
        with staged.temp.open("wb") as stream:
            for start in range(0, labels.size, block_points):
                text = format_labels_bytes(labels[start : start + block_points])
                stream.write(text)
                digest.update(text)
            stream.flush()
            os.fsync(stream.fileno())
        sha256 = digest.hexdigest()
        if before_rename is not None:
            before_rename(sha256)
        staged.commit()
    except BaseException:
        staged.discard()
        raise
    _fsync_folder(path.parent)
    return sha256


def save_session(
    journal: Any,
    labels: NDArray[np.uint8],
    working: NDArray[np.bool_],
    *,
    labels_path: Path,
    requested: str | Path | None,
    scan_folder: Path | None,
    protected: tuple[Path, ...],
    overwrite: bool,
    block_points: int,
) -> Path:
    """Save a session's labels (its caller holds its lock: the arrays do not change).

    The checkpoint and the file's SHA-256 go into the journal before the rename, the file's
    identity after it.
    """
    target = check_save_target(
        requested,
        labels_path=labels_path,
        scan_folder=scan_folder,
        protected=protected,
        overwrite=overwrite,
    )
    editing = target == labels_path

    def record(sha256: str) -> None:
        meta = {"pending_sha256": sha256} if editing else None
        journal.append_checkpoint(labels, working, note=f"saved {target.name}", meta=meta)

    sha256 = write_labels_staged(target, labels, before_rename=record, block_points=block_points)
    if editing:
        journal.set_meta(
            saved_identity=file_identity(target), saved_sha256=sha256, pending_sha256=None
        )
    return target
