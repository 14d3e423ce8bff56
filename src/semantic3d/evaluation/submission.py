"""Submission validation: layout, archive safety and every line of every file, in one pass.

Every problem is collected into one :class:`~semantic3d.core.errors.SubmissionError`:
layout and archive-safety problems (:mod:`semantic3d.evaluation.contents`), then content:
every line an integer 1..8 (CRLF tolerated) and as many lines as the ground truth.
Memory stays constant whatever the file sizes, and a file is never read past one line
more than its scan has points, nor past the bytes those lines can take
(``SubmissionLimits.max_line_bytes`` each): a file that declares more is refused unread,
so a member of gigabytes without a line end costs nothing to refuse.
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


def line_count_problem(name: str, *, expected: int, found: int, more: bool = False) -> str | None:
    """The message for a line-count mismatch (None when the counts agree).

    ``more``: the file goes on after ``found`` lines (reading stopped there).
    """
    if expected == found and not more:
        return None
    if more:
        return (
            f"{name}: expected {expected} lines (one per point of the scan), found more "
            f"than {found} (reading stopped there)"
        )
    return f"{name}: expected {expected} lines (one per point of the scan), found {found}"


def _read_lines(
    stream: LabelStream,
    budget: int | None,
    done: int,
    total: int,
    progress: ProgressCallback | None,
) -> bool:
    """Parse ``stream`` to its end or to ``budget`` lines (and one more to peek).

    Returns whether the stream goes on past the budget; its last line parsed is then the
    peeked one, not counted in the message.
    """
    while True:
        want = _CHECK_CHUNK if budget is None else min(_CHECK_CHUNK, budget - stream.n_lines)
        if want <= 0:
            # One line past the budget was read: is there anything after it?
            return stream.read(1).shape[0] > 0
        if stream.read(want).shape[0] < want:
            return False
        if progress is not None:
            progress(done + stream.bytes_read, total)


def validate_submission(
    submission: Path,
    *,
    challenge: Challenge,
    limits: SubmissionLimits = SubmissionLimits(),
    progress: ProgressCallback | None = None,
) -> None:
    """Check a submission against ``challenge``; raise one error listing every problem.

    Reads every prediction file (values and line counts), but never past one line more
    than its scan has points, and never the ground truth when the protocol knows the
    scan's point count.

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
            # Never read more than one line past the expected count, nor more bytes than
            # those lines can take: a file that is too long is wrong whatever follows,
            # and may be gigabytes of it (with no line end for the count to stop at).
            budget = None if expected is None else expected + 1
            max_bytes = None if budget is None else budget * limits.max_line_bytes
            if max_bytes is not None and entry.size > max_bytes:
                problems.append(
                    f"{entry.name}: {entry.size} bytes once inflated, more than {expected} "
                    f"lines can take (at most {max_bytes} bytes, {limits.max_line_bytes} a "
                    "line); not read"
                )
                continue
            try:
                with entry.open(max_bytes=max_bytes) as handle:
                    stream = LabelStream(
                        handle,
                        source=entry.name,
                        low=protocol.prediction_min,
                        high=protocol.prediction_max,
                    )
                    more = _read_lines(stream, budget, done, total, progress)
            except READ_FAILURES as exc:
                problems.append(read_failure(entry.name, exc))
                continue
            done += entry.size
            if progress is not None:
                progress(done, total)
            problems.extend(stream.problems())
            if expected is not None:
                found = stream.n_lines - 1 if more else stream.n_lines
                mismatch = line_count_problem(entry.name, expected=expected, found=found, more=more)
                if mismatch:
                    problems.append(mismatch)
            logger.info("%s: %d lines checked", entry.name, stream.n_lines)
    if problems:
        raise SubmissionError(problems, source=str(submission))
