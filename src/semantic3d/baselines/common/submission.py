"""Where a baseline's predictions go: which scans to label, under which names, into which files.

A prediction run labels scans found in a folder and writes one ``.labels`` file per scan:

- for a benchmark challenge (``semantic-8``, ``reduced-8``) the scans are the registry's
  (:mod:`semantic3d.datasets`) and each file takes the scan's official submission name
  (``marketsquarefeldkirch4-reduced.labels``);
- for custom data, every ``NAME.txt`` of the folder is a scan and its labels are
  ``NAME.labels`` (the names :func:`~semantic3d.evaluation.custom_challenge` expects).

The output is a folder (``NAME.labels`` plus a ``NAME.labels.json`` run record beside each)
or a zip archive holding only the ``.labels`` files, as the protocol asks of a
submission, with the run records in ``ARCHIVE.zip.json`` beside it. Nothing existing is
replaced unless asked (:func:`refuse_existing_outputs`), and every file appears complete
or not at all.
"""

from __future__ import annotations

import contextlib
import shutil
import uuid
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from semantic3d.core.errors import (
    GroundTruthOutputError,
    Semantic3DError,
    refuse_existing_paths,
)

__all__ = [
    "LABELS_SUFFIX",
    "RUN_RECORD_SUFFIX",
    "ScanToLabel",
    "SubmissionLayoutError",
    "find_scans_to_label",
    "ground_truth_path",
    "is_zip_output",
    "planned_outputs",
    "refuse_existing_outputs",
    "refuse_ground_truth_outputs",
    "refuse_unsafe_outputs",
    "staged_folder",
    "write_atomic_text",
    "write_submission_zip",
]

LABELS_SUFFIX = ".labels"
RUN_RECORD_SUFFIX = ".json"
"""A run record is named after the file it describes plus this suffix (``NAME.labels.json``)."""

_POINTS_SUFFIX = ".txt"


class SubmissionLayoutError(Semantic3DError, ValueError):
    """A folder does not hold the scans asked for, or an output name is not usable."""


@dataclass(frozen=True, slots=True)
class ScanToLabel:
    """One scan of a prediction run.

    Attributes:
        name: the scan's name (registry name, or the file stem for custom data).
        points_path: the ASCII points file.
        output_name: the name of its ``.labels`` file in the output.
    """

    name: str
    points_path: Path
    output_name: str


def find_scans_to_label(data: Path, *, challenge: str | None = None) -> tuple[ScanToLabel, ...]:
    """The scans of ``data`` to label, in a fixed order.

    Args:
        data: a folder of ``NAME.txt`` scans.
        challenge: ``semantic-8`` or ``reduced-8``: every scan of that test split must be
            in ``data`` under its distributed file name; None: every ``NAME.txt``.

    Raises:
        SubmissionLayoutError: ``data`` is not a folder, holds no scan, or lacks scans
            of the challenge (all of them are named), or ``challenge`` is not one.
    """
    if not data.is_dir():
        raise SubmissionLayoutError(f"{data}: expected a folder of NAME.txt scans, found none")
    if challenge is None:
        found = sorted(
            path
            for path in data.iterdir()
            if path.suffix == _POINTS_SUFFIX and not path.name.startswith(".") and path.is_file()
        )
        if not found:
            raise SubmissionLayoutError(f"{data}: expected NAME.txt scans, found none")
        return tuple(ScanToLabel(p.stem, p, p.stem + LABELS_SUFFIX) for p in found)
    from semantic3d.datasets.registry import Split
    from semantic3d.datasets.semantic3d import Semantic3D

    try:
        split = Split(challenge)
    except ValueError:
        split = Split.TRAIN
    if not split.is_challenge:
        raise SubmissionLayoutError(
            f"expected a challenge, one of semantic-8, reduced-8, found {challenge!r}"
        )
    files = Semantic3D(data).scans(split)
    missing = [f.points_path.name for f in files if not f.has_points]
    if missing:
        raise SubmissionLayoutError(
            f"{data}: expected the {len(files)} scans of {challenge}, missing {len(missing)}: "
            + ", ".join(missing)
        )
    return tuple(
        ScanToLabel(f.scan.name, f.points_path, str(f.scan.submission_name)) for f in files
    )


def is_zip_output(out: Path) -> bool:
    """Whether ``out`` names a zip archive (else a folder)."""
    return out.suffix.lower() == ".zip"


def planned_outputs(out: Path, scans: Sequence[ScanToLabel]) -> list[Path]:
    """Every file a run writing ``scans`` to ``out`` creates."""
    if is_zip_output(out):
        return [out, _run_record_path(out)]
    paths: list[Path] = []
    for scan in scans:
        labels = out / scan.output_name
        paths += [labels, _run_record_path(labels)]
    return paths


def refuse_existing_outputs(paths: Sequence[Path], *, overwrite: bool) -> None:
    """Raise :class:`OutputExistsError` naming the first of ``paths`` that exists."""
    refuse_existing_paths(paths, overwrite=overwrite)


def refuse_unsafe_outputs(out: Path, scans: Sequence[ScanToLabel], *, overwrite: bool) -> None:
    """Before a run writing ``scans`` to ``out``: refuse to write over the ground truth of
    any of them (:func:`refuse_ground_truth_outputs`), then over an existing output unless
    ``overwrite`` (:func:`refuse_existing_outputs`)."""
    outputs = planned_outputs(out, scans)
    refuse_ground_truth_outputs([scan.points_path for scan in scans], outputs)
    refuse_existing_outputs(outputs, overwrite=overwrite)


def ground_truth_path(points_path: Path) -> Path:
    """Where a scan's ground truth lives: ``NAME.labels`` beside ``NAME.txt`` (or beside
    any other point file or cache folder of that name)."""
    return points_path.with_suffix(LABELS_SUFFIX)


def refuse_ground_truth_outputs(scans: Sequence[Path], outputs: Sequence[Path]) -> None:
    """Raise :class:`GroundTruthOutputError` when one of ``outputs`` is a scan's ground truth:
    the ``NAME.labels`` of one of ``scans`` (the same path, or another name of the same
    file), or a ``NAME.labels`` with an ASCII scan ``NAME.txt`` / ``NAME.xyz`` beside it.

    ``overwrite`` does not lift this: it is for earlier outputs, and a prediction written
    over a scan's labels would destroy what the scan is scored against.
    """
    from semantic3d.io.formats import ASCII_SUFFIXES

    truths = {ground_truth_path(Path(scan)): Path(scan) for scan in scans}
    resolved = {truth.resolve(): scan for truth, scan in truths.items()}
    for output in map(Path, outputs):
        scan = resolved.get(output.resolve())
        if scan is None and output.exists():
            scan = next((s for t, s in truths.items() if t.exists() and t.samefile(output)), None)
        if scan is None and output.suffix == LABELS_SUFFIX:
            beside = (output.with_suffix(suffix) for suffix in ASCII_SUFFIXES)
            scan = next((path for path in beside if path.is_file()), None)
        if scan is not None:
            raise GroundTruthOutputError(
                f"{output}: is the ground truth of the scan {scan.name} (NAME.labels beside "
                "the scan); a prediction never replaces it, even with overwrite: choose "
                "another output folder"
            )


def _run_record_path(path: Path) -> Path:
    return path.with_name(path.name + RUN_RECORD_SUFFIX)


def write_atomic_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary sibling renamed into place."""
    temp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.partial")
    try:
        temp.write_text(text, encoding="utf-8")
        temp.replace(path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def staged_folder(beside: Path) -> Iterator[Path]:
    """A hidden scratch folder next to ``beside``, removed on exit whatever happens."""
    beside.parent.mkdir(parents=True, exist_ok=True)
    folder = beside.with_name(f".{beside.name}.{uuid.uuid4().hex[:8]}.partial")
    folder.mkdir()
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def write_submission_zip(out: Path, members: Sequence[tuple[str, Path]]) -> None:
    """Zip ``(name, file)`` pairs (deflated) into ``out``, which appears complete or not at all."""
    temp = out.with_name(f".{out.stem}.{uuid.uuid4().hex[:8]}.partial{out.suffix}")
    try:
        with zipfile.ZipFile(temp, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            for name, path in members:
                archive.write(path, arcname=name)
        temp.replace(out)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise
