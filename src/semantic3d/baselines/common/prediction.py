"""The streaming prediction loop every baseline shares, and the protocol a model implements.

A :class:`Predictor` turns a scan's point chunks into :class:`LabelledBlock`\\ s: label values
of some of the scan's points, identified by their position in the scan, in any order
(whole scans in memory, tiles of a tile store, CNN batches). :func:`predict_scan` streams
any supported point file (``io.iter_points``: ASCII, LAS/LAZ, PLY, the cache) through a
predictor, collects the labels in a :class:`~semantic3d.baselines.common.labelbuffer.LabelBuffer`,
writes ``.labels`` in the input's point order and the run record beside it.
:func:`predict_scans` labels many scans with one loaded model into a folder or a zip
ready to submit. No existing file is replaced unless ``overwrite=True``; every file
appears complete or not at all.
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from semantic3d import __version__
from semantic3d.baselines.common.labelbuffer import LabelBuffer
from semantic3d.baselines.common.run import PredictionRun, PredictionRunSet, describe_hardware
from semantic3d.baselines.common.submission import (
    RUN_RECORD_SUFFIX,
    ScanToLabel,
    is_zip_output,
    refuse_existing_outputs,
    refuse_ground_truth_outputs,
    refuse_unsafe_outputs,
    staged_folder,
    write_atomic_text,
    write_submission_zip,
)
from semantic3d.core.errors import Semantic3DError, ShapeError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.core.threads import numba_threads, thread_budget
from semantic3d.core.timeline import span

__all__ = [
    "LabelledBlock",
    "Predictor",
    "Progress",
    "RunProgress",
    "ScanInputError",
    "parallel_scans_limit",
    "predict_scan",
    "predict_scans",
    "scans_at_once",
    "write_prediction_set",
]

Progress = Callable[[int, int], None]
"""``progress(points_labelled, n_points_or_0_while_unknown)``."""

RunProgress = Callable[[int, int, int], None]
"""``progress(scan_index, points_labelled_in_all_scans, n_points_of_all_scans)``; the total
is an estimate (from the files' sizes) until every scan has been read."""


class ScanInputError(Semantic3DError, ValueError):
    """A scan a predictor cannot label: no point, or without an input its model was trained
    with. Raised by a predictor without the scan's name; :func:`predict_scan` puts the
    scan's path in front of the message."""


@dataclass(frozen=True, slots=True)
class LabelledBlock:
    """Labels of some points of a scan.

    Attributes:
        point_indices: ``(m,)`` int64 positions of the points in the scan.
        labels: ``(m,)`` uint8 label values.
        n_scan_points: points in the whole scan (known once the scan has been read).
        tiled: whether the predictor worked tile by tile.
    """

    point_indices: NDArray[np.int64]
    labels: NDArray[np.uint8]
    n_scan_points: int
    tiled: bool = False


class Predictor(Protocol):
    """What a trained baseline offers the prediction loop."""

    @property
    def training_scans(self) -> tuple[str, ...]:
        """Names of the scans it was trained on (recorded with every run)."""
        ...

    @property
    def chunk_size(self) -> int:
        """Points per chunk it wants to read."""
        ...

    def iter_labelled_blocks(
        self, chunks: Iterable[PointCloud], *, workdir: Path
    ) -> Iterator[LabelledBlock]:
        """Label every point of the streamed scan, block by block, in any order.

        ``workdir`` is a scratch folder for tiles and caches, removed after the scan.
        """
        ...


def predict_scan(
    predictor: Predictor,
    points_path: str | Path,
    *,
    out_path: str | Path,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    overwrite: bool = False,
) -> PredictionRun:
    """Label every point of a scan (any format); write ``.labels`` and its run record.

    Args:
        predictor: a trained model.
        points_path: the scan (``.txt``, ``.las``/``.laz``, ``.ply`` or a cache folder).
        out_path: labels file to write (there is no default: the scan's own
            ``NAME.labels`` is usually its ground truth).
        workdir: scratch folder for tiles and the label buffer (default a temporary one).
        progress: called with points labelled so far.
        overwrite: replace ``out_path`` and its run record when they exist.

    Raises:
        OutputExistsError: ``out_path`` or its run record exists and ``overwrite`` is False
            (checked before any work).
        GroundTruthOutputError: ``out_path`` is the scan's own ``NAME.labels``, its ground
            truth (refused even with ``overwrite``).
        ShapeError: the predictor left points without a label.
        ScanInputError: the predictor cannot label this scan (no point, an input missing).
    """
    from semantic3d.io.formats import iter_points
    from semantic3d.io.labels import write_labels

    started = time.perf_counter()
    points_path = Path(points_path)
    out = Path(out_path)
    record = out.with_name(out.name + RUN_RECORD_SUFFIX)
    refuse_ground_truth_outputs([points_path], [out, record])
    refuse_existing_outputs([out, record], overwrite=overwrite)
    chunk_size = predictor.chunk_size
    with tempfile.TemporaryDirectory(prefix="s3d-predict-", dir=workdir) as scratch:
        scratch_dir = Path(scratch)
        done = 0
        tiled = False
        n_points = 0
        with LabelBuffer(scratch_dir / "labels.u8") as buffer:
            chunks = iter_points(points_path, chunk_size=chunk_size, sibling_labels=False)
            try:
                for block in predictor.iter_labelled_blocks(chunks, workdir=scratch_dir):
                    tiled = tiled or block.tiled
                    n_points = block.n_scan_points
                    with span("put labels", points=block.point_indices.size):
                        buffer.put(block.point_indices, block.labels, n_points)
                    done += block.point_indices.size
                    if progress is not None:
                        progress(done, n_points)
            except ScanInputError as exc:
                raise ScanInputError(f"{points_path}: {exc}") from None
            if done != n_points:
                raise ShapeError(
                    f"{points_path}: expected a label for each of {n_points} points, found {done}"
                )
            out.parent.mkdir(parents=True, exist_ok=True)
            with span("write labels", points=n_points):
                written = write_labels(out, buffer.iter_chunks(chunk_size))
    run = PredictionRun(
        scan=str(points_path),
        labels_path=str(out),
        n_points=written,
        runtime_s=time.perf_counter() - started,
        tiled=tiled,
        hardware=describe_hardware(),
        package_version=__version__,
        training_scans=predictor.training_scans,
    )
    write_atomic_text(record, json.dumps(run.to_dict(), indent=2) + "\n")
    return run


def scans_at_once(n_scans: int) -> int:
    """How many of ``n_scans`` scans to label at once by default: one per 4 threads of the
    budget (each scan's tiles use its share), at least 2, at most ``n_scans`` and never
    more than the budget's threads (each scan computes on one at least)."""
    budget = thread_budget()
    return max(1, min(n_scans, budget, max(2, budget // 4)))


def parallel_scans_limit(predictor: Predictor) -> int | None:
    """How many scans ``predictor`` may label at once on threads of one process: its
    ``max_parallel_scans`` (at least 1), or None when it declares none (the caller's
    ``parallel_scans`` is then trusted)."""
    limit = getattr(predictor, "max_parallel_scans", None)
    return None if limit is None else max(1, int(limit))


def predict_scans(
    predictor: Predictor,
    scans: Sequence[ScanToLabel],
    out: str | Path,
    *,
    workdir: str | Path | None = None,
    progress: RunProgress | None = None,
    overwrite: bool = False,
    parallel_scans: int = 1,
) -> PredictionRunSet:
    """Label ``scans`` with one model into a folder, or a zip archive when ``out`` ends in .zip.

    A folder gets ``NAME.labels`` and a ``NAME.labels.json`` run record per scan (created
    if needed); a zip holds only the ``.labels`` files (a submission, see
    :mod:`semantic3d.baselines.common.submission`) and the run records go to
    ``ARCHIVE.zip.json``. Every file is written under a temporary name and renamed when
    complete: after an error or Ctrl-C a folder holds the scans finished so far and a
    zip does not exist.

    ``parallel_scans`` > 1 labels that many scans at a time (at most the thread budget:
    :func:`~semantic3d.core.threads.thread_budget`), each on its own thread, for a
    predictor whose work releases the GIL and is safe to run from several threads (the
    covariance baseline's compiled kernels): the serial parts of one scan then overlap the
    parallel parts of another. A predictor with a ``max_parallel_scans`` attribute caps it
    (:func:`parallel_scans_limit`: 1 where its kernels must not run on several threads at
    once, or on a cluster that already labels a scan's tiles in parallel). Every scan's
    labels are the same as when labelled alone; memory is that of the scans labelled at
    once. After an error or Ctrl-C the scans being labelled stop at their next block of
    labels and no new scan starts.

    Raises:
        OutputExistsError: an output exists and ``overwrite`` is False (checked before
            any work, naming the first one).
        GroundTruthOutputError: an output is the ground truth of one of ``scans``.
        ValueError: ``parallel_scans`` < 1.
    """
    from semantic3d.io.formats import estimate_point_count

    if parallel_scans < 1:
        raise ValueError(f"parallel_scans: expected at least 1, found {parallel_scans}")
    limit = parallel_scans_limit(predictor)
    if limit is not None:
        parallel_scans = min(parallel_scans, limit)
    # each scan labelled at once computes on a thread at least: the budget caps them
    parallel_scans = min(parallel_scans, thread_budget())
    started = time.perf_counter()
    out = Path(out)
    refuse_unsafe_outputs(out, scans, overwrite=overwrite)
    estimates = [estimate_point_count(scan.points_path).n_points for scan in scans]
    runs: list[PredictionRun] = []

    def predict_all(folder: Path) -> None:
        if parallel_scans > 1 and len(scans) > 1:
            runs.extend(
                _predict_in_threads(
                    predictor,
                    scans,
                    folder,
                    estimates,
                    workdir=workdir,
                    progress=progress,
                    overwrite=overwrite or folder != out,
                    n_threads=min(parallel_scans, len(scans)),
                )
            )
            return
        for index, scan in enumerate(scans):
            before = sum(run.n_points for run in runs)

            def update(done: int, total: int, index: int = index, before: int = before) -> None:
                if total:
                    estimates[index] = total
                if progress is not None:
                    progress(index, before + done, before + sum(estimates[index:]))

            runs.append(
                predict_scan(
                    predictor,
                    scan.points_path,
                    out_path=folder / scan.output_name,
                    workdir=workdir,
                    progress=update,
                    overwrite=overwrite or folder != out,
                )
            )

    return write_prediction_set(out, scans, predict_all, started=started, runs=runs)


def write_prediction_set(
    out: Path,
    scans: Sequence[ScanToLabel],
    label_all: Callable[[Path], object],
    *,
    started: float,
    runs: list[PredictionRun],
) -> PredictionRunSet:
    """Run ``label_all(folder)``, which labels every scan into ``folder / scan.output_name``
    and appends each scan's run to ``runs``, so that ``out`` ends as a folder or a zip.

    A folder is written in place (each file staged by its writer). For a zip the scans are
    labelled into a hidden scratch folder, zipped into ``out`` (complete or absent) and the
    runs recorded in ``ARCHIVE.zip.json``; the runs' ``labels_path`` name the members.
    """
    if not is_zip_output(out):
        out.mkdir(parents=True, exist_ok=True)
        label_all(out)
        return PredictionRunSet(str(out), tuple(runs), time.perf_counter() - started)
    with staged_folder(out) as folder:
        label_all(folder)
        write_submission_zip(out, [(scan.output_name, folder / scan.output_name) for scan in scans])
    runs[:] = [
        dataclasses.replace(run, labels_path=f"{out}:{scan.output_name}")
        for run, scan in zip(runs, scans, strict=True)
    ]
    result = PredictionRunSet(str(out), tuple(runs), time.perf_counter() - started)
    write_atomic_text(
        out.with_name(out.name + RUN_RECORD_SUFFIX), json.dumps(result.to_dict(), indent=2) + "\n"
    )
    return result


class _StoppedError(Exception):
    """Raised in a scan's thread when another scan failed or the run was interrupted."""


def _predict_in_threads(
    predictor: Predictor,
    scans: Sequence[ScanToLabel],
    folder: Path,
    estimates: list[int],
    *,
    workdir: str | Path | None,
    progress: RunProgress | None,
    overwrite: bool,
    n_threads: int,
) -> list[PredictionRun]:
    """:func:`predict_scan` of every scan, ``n_threads`` at a time; runs in input order."""
    lock = threading.Lock()
    stop = threading.Event()
    done = [0] * len(scans)

    def label(index: int) -> PredictionRun:
        def update(labelled: int, total: int) -> None:
            if stop.is_set():
                raise _StoppedError
            with lock:
                if total:
                    estimates[index] = total
                done[index] = labelled
                if progress is not None:
                    progress(
                        index,
                        sum(done),
                        sum(max(n, d) for n, d in zip(estimates, done, strict=True)),
                    )

        if stop.is_set():
            raise _StoppedError
        with numba_threads(share):  # each scan's kernels and tiles: its share of the budget
            return predict_scan(
                predictor,
                scans[index].points_path,
                out_path=folder / scans[index].output_name,
                workdir=workdir,
                progress=update,
                overwrite=overwrite,
            )

    share = max(1, thread_budget() // n_threads)

    pool = ThreadPoolExecutor(max_workers=n_threads, thread_name_prefix="predict-scan")
    futures = [pool.submit(label, index) for index in range(len(scans))]
    try:
        # the first failure in time, not in input order, stops the others
        finished, _ = wait(futures, return_when=FIRST_EXCEPTION)
        for future in finished:
            error = future.exception()
            if error is not None and not isinstance(error, _StoppedError):
                raise error
        return [future.result() for future in futures]
    except BaseException:
        stop.set()
        for future in futures:
            future.cancel()
        raise
    finally:
        pool.shutdown(wait=True)
