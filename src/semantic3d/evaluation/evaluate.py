"""``evaluate_submission``: the reference evaluator of the semantic3D.net protocol.

One function for every shell: the CLI and the benchmark server both call it. Each scan's
ground truth and prediction are streamed side by side, chunk by chunk, into a
:class:`~semantic3d.metrics.ConfusionMatrix`; memory stays constant whatever the file
sizes. Runs of one-digit lines in both files (the benchmark's own shape) are checked and
counted in one compiled pass (:mod:`semantic3d.evaluation._digit_pair_kernel`); every other
line goes through the general parsers, which report its problems. Validation happens in
the same pass (values, line counts) and every problem is collected before anything is
reported, so an invalid submission gets one :class:`~semantic3d.core.errors.SubmissionError`
listing them all.
"""

from __future__ import annotations

import io
import logging
import os
import stat
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from types import ModuleType

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import DataFormatError, SubmissionError
from semantic3d.core.threads import map_in_threads, thread_budget
from semantic3d.evaluation.challenge import Challenge, ChallengeScan
from semantic3d.evaluation.contents import (
    READ_FAILURES,
    SubmissionFile,
    SubmissionLimits,
    open_submission,
    read_failure,
)
from semantic3d.evaluation.protocol import Protocol, load_protocol
from semantic3d.evaluation.result import EvaluationResult, MethodInfo, ScanResult
from semantic3d.evaluation.submission import ProgressCallback, line_count_problem
from semantic3d.io.labelstream import LabelStream
from semantic3d.metrics.confusion import ConfusionMatrix

logger = logging.getLogger(__name__)

DEFAULT_EVALUATION_CHUNK = 1 << 22
"""Label pairs accumulated at a time (4 Mi: two 4 MiB value buffers)."""


@dataclass(frozen=True, slots=True)
class ScanEvaluation:
    """One scan of a submission, scored: its matrix, or None when its prediction has problems."""

    matrix: ConfusionMatrix | None
    problems: tuple[str, ...]


ScanMapper = Callable[[Callable[[int], ScanEvaluation], Sequence[int]], Iterable[ScanEvaluation]]
"""``map_scans(function, scan_indices)``: results in input order (e.g. a Dask cluster's map)."""


class _Progress:
    def __init__(self, callback: ProgressCallback | None, total: int) -> None:
        self.callback = callback
        self.total = total
        self.done = 0

    def report(self, extra: int = 0) -> None:
        if self.callback is not None:
            self.callback(min(self.done + extra, self.total), self.total)


class _PredictionUnreadableError(Exception):
    """The prediction stream failed mid-way (corrupt member, size cap)."""


@contextmanager
def _reading_prediction() -> Iterator[None]:
    """Mark archive failures while reading the prediction as the submission's fault."""
    try:
        yield
    except READ_FAILURES as exc:
        raise _PredictionUnreadableError(exc) from exc


class _Ahead:
    """A one-thread pool, or (``threaded`` False) one that runs each call at once."""

    def __init__(self, threaded: bool) -> None:
        self.pool = (
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="semantic3d-truth")
            if threaded
            else None
        )

    def __enter__(self) -> _Ahead:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True)

    def submit(
        self, function: Callable[[int], NDArray[np.uint8]], argument: int
    ) -> Future[NDArray[np.uint8]]:
        if self.pool is not None:
            return self.pool.submit(function, argument)
        done: Future[NDArray[np.uint8]] = Future()
        try:
            done.set_result(function(argument))
        except BaseException as exc:
            done.set_exception(exc)
        return done


def _stream_pair(
    truth: LabelStream,
    pred: LabelStream,
    matrix: ConfusionMatrix,
    *,
    chunk_size: int,
    progress: _Progress,
) -> None:
    """Count every (truth, prediction) pair of the two streams into ``matrix``, checking both.

    Runs of ``d\\n`` lines in both files (the benchmark's shape) are parsed and counted in
    one pass by the compiled pair counter; any other line goes to the general parsers
    (which report its problems), a window of lines at a time, and a file of another shape
    falls back to them altogether after a few windows.
    """
    counter = _DigitPairCounter.for_streams(truth, pred, matrix.n_classes)
    step = _RETRY_PAIRS if counter is not None else chunk_size
    while counter is not None and step < chunk_size:
        counted, other_shape = counter.count(truth, pred, progress)
        if counted:
            step = _RETRY_PAIRS
        elif other_shape:
            step = min(2 * step, chunk_size)
        size = step if other_shape else chunk_size
        n = _count_with_prediction(truth.read(size), pred, matrix)
        progress.report(truth.bytes_read)
        if n < size:
            break
    else:
        _stream_values(truth, pred, matrix, chunk_size=chunk_size, progress=progress)
    if counter is not None:
        counter.add_to(matrix)
    truth.drain()
    with _reading_prediction():
        pred.drain()


def _count_with_prediction(
    y_true: NDArray[np.uint8], pred: LabelStream, matrix: ConfusionMatrix
) -> int:
    """Parse as many prediction values as ``y_true`` holds and count the pairs into
    ``matrix`` (no longer once the prediction has problems); the values parsed."""
    with _reading_prediction():
        y_pred = pred.read(y_true.shape[0])
    n = y_pred.shape[0]
    if n and not pred.has_problems:
        matrix.update(y_true[:n], y_pred)
    return int(n)


_BLOCK_BYTES = 1 << 20
"""Bytes read from each file at a time: small enough that the pair counter finds the two
blocks still in cache (on one thread, 4 MiB blocks gave 0.6x the pairs/s of 1 MiB here,
256 KiB 0.85x)."""
_DIGIT_PAIR_READ = _BLOCK_BYTES // 2
"""Bytes of each file the pair counter is given at least, but at the ends of the files."""
_RETRY_PAIRS = 1 << 12
"""Pairs the general parsers take after a window of another shape (one counter window),
doubled while the counter counts nothing, up to the chunk size: then they take the rest."""


def _digit_ranges(
    truth_range: tuple[int, int], pred_range: tuple[int, int], n_classes: int
) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """The single-digit values of the truth's and the prediction's ranges; None if either
    has none."""
    (t_low, t_high), (p_low, p_high) = truth_range, pred_range
    t_high, p_high = min(t_high, 9, n_classes), min(p_high, 9, n_classes)
    if not (0 <= t_low <= t_high and 0 <= p_low <= p_high):
        return None
    return (t_low, t_high), (p_low, p_high)


def _count_digit_files(
    truth: io.RawIOBase,
    pred: io.RawIOBase,
    matrix: ConfusionMatrix,
    truth_range: tuple[int, int],
    pred_range: tuple[int, int],
    progress: _Progress,
) -> int | None:
    """Count two regular files of ``d\\n`` lines of the same length into ``matrix``; their
    lines. None (``matrix`` untouched) for anything else: a stream that is not a plain
    file, files of different sizes, a small text, any line of another shape or a value out
    of range. Read with positioned reads, from the start whatever the handles' positions.
    """
    if not (hasattr(os, "pread") and isinstance(truth, io.FileIO) and isinstance(pred, io.FileIO)):
        return None
    ranges = _digit_ranges(truth_range, pred_range, matrix.n_classes)
    try:
        truth_status, pred_status = os.fstat(truth.fileno()), os.fstat(pred.fileno())
    except OSError:
        return None
    size = truth_status.st_size
    if (
        ranges is None
        or not (stat.S_ISREG(truth_status.st_mode) and stat.S_ISREG(pred_status.st_mode))
        or pred_status.st_size != size
        or size % 2
        or size <= _BLOCK_BYTES  # a small text: the general parsers, numba not loaded
    ):
        return None
    from semantic3d.evaluation import _digit_pair_kernel as kernel

    n_pairs = size // 2
    table = np.zeros((matrix.n_classes + 1,) * 2, dtype=np.int64)
    if not kernel.count_files(
        truth.fileno(),
        pred.fileno(),
        n_pairs,
        *ranges,
        table,
        lambda lines: progress.report(2 * lines),
    ):
        return None
    matrix.add_counts(table)
    return n_pairs


class _DigitPairCounter:
    """The compiled counter of ``d\\n`` pairs, driven over two streams' buffers."""

    def __init__(self, truth_range: tuple[int, int], pred_range: tuple[int, int], size: int):
        self.truth_range = truth_range
        self.pred_range = pred_range
        self.table = np.zeros((size, size), dtype=np.int64)
        # Short texts go to the general parsers (numpy for small ones) until the counter has
        # run: loading numba costs more than parsing a test file.
        self.min_pairs = _DIGIT_PAIR_READ // 2
        self.kernel: ModuleType | None = None

    @classmethod
    def for_streams(
        cls, truth: LabelStream, pred: LabelStream, n_classes: int
    ) -> _DigitPairCounter | None:
        """A counter for the single-digit values both streams accept; None if there are none."""
        ranges = _digit_ranges(truth.value_range, pred.value_range, n_classes)
        return None if ranges is None else cls(*ranges, n_classes + 1)

    def count(self, truth: LabelStream, pred: LabelStream, progress: _Progress) -> tuple[int, bool]:
        """Count pairs until a file ends or a window holds another line; (pairs, the latter)."""
        counted = 0
        while True:
            t_buf, t_at, t_end = truth.buffered(_DIGIT_PAIR_READ)
            with _reading_prediction():
                p_buf, p_at, p_end = pred.buffered(_DIGIT_PAIR_READ)
            n = min(t_end - t_at, p_end - p_at) // 2
            if n < self.min_pairs:
                return counted, False
            if self.kernel is None:
                from semantic3d.evaluation import _digit_pair_kernel

                self.kernel = _digit_pair_kernel
                self.min_pairs = _digit_pair_kernel.WINDOW
            kernel = self.kernel
            got = kernel.count_pairs(
                t_buf, t_at, p_buf, p_at, n, self.truth_range, self.pred_range, self.table
            )
            truth.skip_checked_lines(got, 2 * got)
            pred.skip_checked_lines(got, 2 * got)
            counted += got
            progress.report(truth.bytes_read)
            if got < n - n % kernel.WINDOW:
                return counted, True

    def add_to(self, matrix: ConfusionMatrix) -> None:
        matrix.add_counts(self.table)


def _stream_values(
    truth: LabelStream,
    pred: LabelStream,
    matrix: ConfusionMatrix,
    *,
    chunk_size: int,
    progress: _Progress,
) -> None:
    """Accumulate (truth, prediction) chunks of parsed values until either stream ends.

    The ground truth is parsed one chunk ahead in a worker thread (the kernels and file
    reads release the GIL) while this thread inflates and parses the prediction; with a
    thread budget of one, both in this thread.
    """
    with _Ahead(thread_budget() > 1) as pool:
        pending: Future[NDArray[np.uint8]] | None = pool.submit(truth.read, chunk_size)
        while pending is not None:
            y_true = pending.result()
            full = y_true.shape[0] == chunk_size
            pending = pool.submit(truth.read, chunk_size) if full else None
            n = _count_with_prediction(y_true, pred, matrix)
            progress.report(truth.bytes_read)
            if n < y_true.shape[0]:
                break
        if pending is not None:
            pending.result()


def _evaluate_scan(
    scan: ChallengeScan,
    gt_path: Path,
    entry: SubmissionFile,
    *,
    protocol: Protocol,
    chunk_size: int,
    problems: list[str],
    progress: _Progress,
) -> ConfusionMatrix | None:
    """Count one (ground truth, prediction) pair; None when the prediction has problems.

    Two regular files of ``d\\n`` lines are counted by the compiled file counter; anything
    else (or any problem in them) is streamed through the general parsers.
    """
    matrix = ConfusionMatrix(protocol.n_classes)
    truth_range = (0, protocol.n_classes)
    pred_range = (protocol.prediction_min, protocol.prediction_max)
    with gt_path.open("rb", buffering=0) as gt_handle:
        try:
            pred_handle = entry.open()
        except READ_FAILURES as exc:
            problems.append(read_failure(entry.name, exc))
            return None
        with pred_handle:
            n_lines = _count_digit_files(
                gt_handle, pred_handle, matrix, truth_range, pred_range, progress
            )
            if n_lines is not None:
                truth_lines, pred_lines, scan_problems = n_lines, n_lines, []
            else:
                truth = LabelStream(
                    gt_handle,
                    source=str(gt_path),
                    low=truth_range[0],
                    high=truth_range[1],
                    block_size=_BLOCK_BYTES,
                )
                pred = LabelStream(
                    pred_handle,
                    source=entry.name,
                    low=pred_range[0],
                    high=pred_range[1],
                    block_size=_BLOCK_BYTES,
                )
                try:
                    _stream_pair(truth, pred, matrix, chunk_size=chunk_size, progress=progress)
                except _PredictionUnreadableError as exc:
                    cause = exc.__cause__ if exc.__cause__ is not None else exc
                    problems.append(read_failure(entry.name, cause))
                    return None
                truth_problems = truth.problems()
                if truth_problems:
                    raise DataFormatError("invalid ground truth: " + "; ".join(truth_problems))
                truth_lines, pred_lines, scan_problems = (
                    truth.n_lines,
                    pred.n_lines,
                    pred.problems(),
                )
    if scan.n_points is not None and scan.n_points != truth_lines:
        raise DataFormatError(
            f"expected {scan.n_points} lines for scan {scan.name} (protocol "
            f"v{protocol.version}), found {truth_lines}",
            path=str(gt_path),
        )
    mismatch = line_count_problem(entry.name, expected=truth_lines, found=pred_lines)
    if mismatch:
        scan_problems.append(mismatch)
    problems.extend(scan_problems)
    return None if scan_problems else matrix


def evaluate_submitted_scan(
    submission: Path,
    scan_index: int,
    *,
    challenge: Challenge,
    limits: SubmissionLimits = SubmissionLimits(),
    chunk_size: int = DEFAULT_EVALUATION_CHUNK,
) -> ScanEvaluation:
    """Score scan ``challenge.scans[scan_index]`` of a submission (a picklable unit of work).

    The submission's layout problems are left to :func:`evaluate_submission`; a scan the
    submission lacks gives no matrix and no problem.
    """
    protocol = load_protocol(challenge.protocol_version)
    scan = challenge.scans[scan_index]
    challenge.require_ground_truth()
    gt_path = scan.ground_truth
    assert gt_path is not None  # require_ground_truth() checked it
    with open_submission(submission, challenge=challenge, limits=limits) as contents:
        entry = contents.files.get(scan.submission_name)
        if entry is None:
            return ScanEvaluation(None, ())
        problems: list[str] = []
        matrix = _evaluate_scan(
            scan,
            gt_path,
            entry,
            protocol=protocol,
            chunk_size=chunk_size,
            problems=problems,
            progress=_Progress(None, 0),
        )
    return ScanEvaluation(matrix, tuple(problems))


def evaluate_submission(
    submission: Path,
    *,
    challenge: Challenge,
    method: MethodInfo | None = None,
    limits: SubmissionLimits = SubmissionLimits(),
    progress: ProgressCallback | None = None,
    chunk_size: int = DEFAULT_EVALUATION_CHUNK,
    map_scans: ScanMapper | None = None,
) -> EvaluationResult:
    """Validate and score a submission (zip archive or folder) against ``challenge``.

    Args:
        submission: a ``.zip`` or a folder of ``.labels`` files named as the challenge says.
        challenge: from :func:`load_challenge` (with ground truth) or
            :func:`custom_challenge`.
        method: name, runtime and hardware shown in reports.
        limits: archive safety caps.
        progress: called as ``progress(done_bytes, total_bytes)`` of ground truth read.
        chunk_size: label pairs accumulated at a time.
        map_scans: scores the scans elsewhere (:func:`evaluate_submitted_scan` per scan,
            e.g. on a Dask cluster); default: on threads of this process, as many scans
            at once as the thread budget has threads; same result.

    Raises:
        SubmissionError: the submission is invalid; ``.problems`` lists every problem.
        MissingGroundTruthError: a scan of the challenge has no ground truth.
        DataFormatError: a ground-truth file is invalid or disagrees with the protocol.
    """
    challenge.require_ground_truth()
    protocol = load_protocol(challenge.protocol_version)
    total = ConfusionMatrix(protocol.n_classes)
    per_scan: list[ScanResult] = []
    gt_bytes = sum(s.ground_truth.stat().st_size for s in challenge.scans if s.ground_truth)
    tracker = _Progress(progress, gt_bytes)
    if map_scans is None and len(challenge.scans) > 1 and thread_budget() > 1:
        # scans at the same time, each on its share of the threads (merged in order: the
        # same result); a scan with two threads parses its truth beside its prediction
        at_once = min(len(challenge.scans), thread_budget())
        map_scans = partial(_map_in_threads, n_threads=at_once)
    if map_scans is not None:
        return _evaluate_mapped(
            submission,
            challenge=challenge,
            protocol=protocol,
            method=method,
            limits=limits,
            tracker=tracker,
            chunk_size=chunk_size,
            map_scans=map_scans,
        )
    with open_submission(submission, challenge=challenge, limits=limits) as contents:
        problems = contents.problems
        for scan in challenge.scans:
            gt_path = scan.ground_truth
            if gt_path is None:  # unreachable after require_ground_truth(); keeps mypy sure
                continue
            entry = contents.files.get(scan.submission_name)
            if entry is not None:
                matrix = _evaluate_scan(
                    scan,
                    gt_path,
                    entry,
                    protocol=protocol,
                    chunk_size=chunk_size,
                    problems=problems,
                    progress=tracker,
                )
                if matrix is not None and not problems:
                    total.merge(matrix)
                    per_scan.append(
                        ScanResult(
                            scan.name,
                            scan.submission_name,
                            matrix.compute(),
                            matrix.compute_scores(),
                        )
                    )
            tracker.done += gt_path.stat().st_size
            tracker.report()
    return _result(submission, challenge, protocol, method, problems, total, per_scan)


def _map_in_threads(
    function: Callable[[int], ScanEvaluation], items: Sequence[int], *, n_threads: int
) -> Iterator[ScanEvaluation]:
    share = max(1, thread_budget() // n_threads)
    return map_in_threads(
        function, items, n_threads=n_threads * share, numba_threads_per_task=share, name="s3d-scan"
    )


def _evaluate_mapped(
    submission: Path,
    *,
    challenge: Challenge,
    protocol: Protocol,
    method: MethodInfo | None,
    limits: SubmissionLimits,
    tracker: _Progress,
    chunk_size: int,
    map_scans: ScanMapper,
) -> EvaluationResult:
    """:func:`evaluate_submission` with the scans scored by ``map_scans``, merged in order."""
    total = ConfusionMatrix(protocol.n_classes)
    per_scan: list[ScanResult] = []
    with open_submission(submission, challenge=challenge, limits=limits) as contents:
        problems = list(contents.problems)
        present = [
            index
            for index, scan in enumerate(challenge.scans)
            if scan.submission_name in contents.files
        ]
    task = partial(
        evaluate_submitted_scan,
        submission,
        challenge=challenge,
        limits=limits,
        chunk_size=chunk_size,
    )
    for index, outcome in zip(present, map_scans(task, present), strict=True):
        scan = challenge.scans[index]
        problems.extend(outcome.problems)
        if outcome.matrix is not None and not problems:
            total.merge(outcome.matrix)
            per_scan.append(
                ScanResult(
                    scan.name,
                    scan.submission_name,
                    outcome.matrix.compute(),
                    outcome.matrix.compute_scores(),
                )
            )
        if scan.ground_truth is not None:
            tracker.done += scan.ground_truth.stat().st_size
        tracker.report()
    return _result(submission, challenge, protocol, method, problems, total, per_scan)


def _result(
    submission: Path,
    challenge: Challenge,
    protocol: Protocol,
    method: MethodInfo | None,
    problems: list[str],
    total: ConfusionMatrix,
    per_scan: list[ScanResult],
) -> EvaluationResult:
    if problems:
        raise SubmissionError(problems, source=str(submission))
    scores = total.compute_scores()
    logger.info(
        "%s: %s, mIoU %.4f, OA %.4f over %d points",
        submission,
        challenge.name,
        scores.mean_iou,
        scores.overall_accuracy,
        scores.n_points,
    )
    return EvaluationResult(
        challenge=challenge.name,
        protocol_version=protocol.version,
        confusion=total.compute(),
        scores=scores,
        n_points=scores.n_points,
        method=method,
        per_scan=tuple(per_scan),
    )
