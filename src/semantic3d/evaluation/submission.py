"""Submission validation: layout, archive safety and every line of every file, in one pass.

Every problem is collected into one :class:`~semantic3d.core.errors.SubmissionError`:
layout and archive-safety problems (:mod:`semantic3d.evaluation.contents`), then content:
every line an integer 1..8 (CRLF tolerated) and as many lines as the ground truth.
Memory stays constant whatever the file sizes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from semantic3d.core.errors import DataFormatError, SubmissionError
from semantic3d.evaluation.challenge import Challenge, ChallengeScan
from semantic3d.evaluation.contents import (
    READ_FAILURES,
    SubmissionLimits,
    open_submission,
    read_failure,
)
from semantic3d.evaluation.protocol import load_protocol
from semantic3d.io.labelstream import LabelStream

logger = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int], None]
"""``progress(done, total)``: bytes processed so far and in all."""

_CHECK_CHUNK = 1 << 22  # values parsed between progress reports

__all__ = [
    "ProgressCallback",
    "SubmissionLimits",
    "count_ground_truth_lines",
    "expected_lines",
    "line_count_problem",
    "validate_submission",
]


def count_ground_truth_lines(scan: ChallengeScan, *, block_size: int | None = None) -> int:
    """Lines of the scan's ground-truth file, checking every value is 0..8.

    Raises:
        DataFormatError: the ground truth has non-integer or out-of-range lines.
    """
    if scan.ground_truth is None:
        raise DataFormatError(f"scan {scan.name}: no ground-truth file to count lines of")
    protocol = load_protocol()
    with scan.ground_truth.open("rb", buffering=0) as handle:
        kwargs = {} if block_size is None else {"block_size": block_size}
        stream = LabelStream(
            handle, source=str(scan.ground_truth), low=0, high=protocol.n_classes, **kwargs
        )
        stream.drain()
    problems = stream.problems()
    if problems:
        raise DataFormatError("invalid ground truth: " + "; ".join(problems))
    return stream.n_lines


def expected_lines(scan: ChallengeScan) -> int | None:
    """The line count a submission file must have: the protocol's, else the ground truth's."""
    if scan.n_points is not None:
        return scan.n_points
    if scan.ground_truth is not None:
        return count_ground_truth_lines(scan)
    return None


def line_count_problem(name: str, *, expected: int, found: int) -> str | None:
    """The message for a line-count mismatch (None when the counts agree)."""
    if expected == found:
        return None
    return f"{name}: expected {expected} lines (one per point of the scan), found {found}"


def validate_submission(
    submission: Path,
    *,
    challenge: Challenge,
    limits: SubmissionLimits = SubmissionLimits(),
    progress: ProgressCallback | None = None,
) -> None:
    """Check a submission against ``challenge``; raise one error listing every problem.

    Reads every prediction file in full (values and line counts) but never the ground
    truth when the protocol knows the scan's point count.

    Raises:
        SubmissionError: the submission is invalid; ``.problems`` lists every problem.
        DataFormatError: a ground-truth file needed for a line count is itself invalid.
    """
    protocol = load_protocol(challenge.protocol_version)
    with open_submission(submission, challenge=challenge, limits=limits) as contents:
        problems = contents.problems
        total = contents.total_bytes
        done = 0
        for scan in challenge.scans:
            entry = contents.files.get(scan.submission_name)
            if entry is None:
                continue
            expected = expected_lines(scan)
            try:
                with entry.open() as handle:
                    stream = LabelStream(
                        handle,
                        source=entry.name,
                        low=protocol.prediction_min,
                        high=protocol.prediction_max,
                    )
                    while stream.read(_CHECK_CHUNK).shape[0] == _CHECK_CHUNK:
                        if progress is not None:
                            progress(done + stream.bytes_read, total)
            except READ_FAILURES as exc:
                problems.append(read_failure(entry.name, exc))
                continue
            done += entry.size
            if progress is not None:
                progress(done, total)
            problems.extend(stream.problems())
            if expected is not None:
                mismatch = line_count_problem(entry.name, expected=expected, found=stream.n_lines)
                if mismatch:
                    problems.append(mismatch)
            logger.info("%s: %d lines checked", entry.name, stream.n_lines)
    if problems:
        raise SubmissionError(problems, source=str(submission))
