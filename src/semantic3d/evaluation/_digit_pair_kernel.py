"""The compiled counter of ``d\\n`` line pairs: ground truth and prediction text, counted at once.

Hand-written hot path. A benchmark file holds one digit a line, so a scan's two files are
read side by side as 16-bit words, a line each: the word minus ``"0\\n"`` is the label value
exactly when it is at most 9. One pass checks both values against their ranges and counts
the pair in the confusion table, where parsing each file into a value array, checking the
arrays' ranges and counting them (what :class:`~semantic3d.io.labelstream.LabelStream` and
:class:`~semantic3d.metrics.ConfusionMatrix` do for any text) reads and writes each label
four times more. No library parses and counts in one pass; the general parsers stay the
reference and handle every other shape (CRLF, several digits, bad lines).

The pass works on runs, not lines: labels come in runs, so 64 pairs at a time become one
mask of the pairs that change (two vector comparisons, :mod:`semantic3d.core.bits`), and
only a change costs a scalar step (the run before it added to its cell, the new pair
checked). On a simulated scan against its prediction (a change every ~120 lines) that is
~0.1 ns a pair on one core, against ~0.5 ns for checking every pair in blocks of 32 and
counting the blocks of one repeated pair at once; labels that change every few lines are
counted pair by pair, at the rate of before.

Two drivers. :func:`count_digit_pairs` counts text another reader has buffered (any
stream: a file, a zip member). :func:`count_file_pairs` reads two regular files itself,
with ``pread`` on each run's own buffers, so a scan's whole text is counted without the
interpreter between its blocks: with many scans at once, the interpreter's lock taken
several times a block (a read of each file, the count, the streams' bookkeeping) left
threads waiting for it.

The lines are taken in windows of :data:`WINDOW` pairs, the windows split into one run per
thread. A run stops at its first window holding anything else; what is counted is the
prefix of whole windows before the first such window, so the caller can hand that window
to the general parsers, which report its problems. Counts are integers: the same whatever
the threads.
"""

from __future__ import annotations

from collections.abc import Callable

import numba as nb
import numpy as np
from numpy.typing import NDArray

from semantic3d.core.bits import CHANGE_SPAN, bit_count, trailing_zeros, word_changes
from semantic3d.io._positioned_reads import read_fully

WINDOW = 4096
"""Line pairs checked at once: a window either counts whole or not at all."""

_LANES = 8  # a busy span's interleaved counters: pairs that differ wait on no one cell
_SPAN = CHANGE_SPAN
"""Pairs whose changes one mask finds (:func:`~semantic3d.core.bits.word_changes`)."""
_BUSY = 12
"""Changes in one span above which its pairs are counted one by one: on one core here a
change costs about 4 ns (found, a branch mispredicted, the new pair checked) and a pair
counted alone about 0.8 ns, so the two cost the same at about 12 changes in 64 (labels in
random runs of mean length 3 to 16: 0.99-1.37 times the rate of counting every pair)."""
_PAIR_ZERO = 0x0A30
"""``"0\\n"`` read as one little-endian 16-bit word."""
FILE_PIECE_PAIRS = 1 << 25
"""Line pairs :func:`count_files` counts in one call of :func:`count_file_pairs` (64 MiB of
each file)."""
BLOCK_WINDOWS = 64
"""Windows :func:`count_file_pairs` reads of each file at a time (512 KiB of text): the two
blocks stay in cache for the count, as :class:`~semantic3d.io.labelstream.LabelStream`'s
blocks do for :func:`count_digit_pairs`."""
if WINDOW % _SPAN or _SPAN % _LANES:
    raise ValueError("a window is whole spans, a span whole rows of _LANES")


@nb.njit(cache=True, nogil=True, inline="always")
def _in_range(
    t: np.uint16,
    p: np.uint16,
    t_low: np.uint16,
    t_span: np.uint16,
    p_low: np.uint16,
    p_span: np.uint16,
) -> np.bool_:  # pragma: no cover - compiled
    """Whether words ``t`` and ``p`` are ``d\\n`` lines of values in their ranges."""
    return (np.uint16(np.uint16(t - np.uint16(_PAIR_ZERO)) - t_low) <= t_span) & (
        np.uint16(np.uint16(p - np.uint16(_PAIR_ZERO)) - p_low) <= p_span
    )


@nb.njit(cache=True, nogil=True, inline="always")
def _count_busy_span(
    truth: NDArray[np.uint16],
    pred: NDArray[np.uint16],
    start: int,
    lanes: NDArray[np.int64],
    t_low: np.uint16,
    t_span: np.uint16,
    p_low: np.uint16,
    p_span: np.uint16,
    sign: int,
) -> bool:  # pragma: no cover - compiled
    """Add ``sign`` for each pair of the span from ``start`` to its cell, a lane each of
    :data:`_LANES` neighbours; whether every pair is in range (one vector pass)."""
    worst_truth = np.uint16(0)
    worst_pred = np.uint16(0)
    for k in range(start, start + _SPAN):
        worst_truth = max(
            worst_truth, np.uint16(np.uint16(truth[k] - np.uint16(_PAIR_ZERO)) - t_low)
        )
        worst_pred = max(worst_pred, np.uint16(np.uint16(pred[k] - np.uint16(_PAIR_ZERO)) - p_low))
    for k in range(start, start + _SPAN, _LANES):
        for lane in range(_LANES):
            cell = ((truth[k + lane] & 15) << 4) | (pred[k + lane] & 15)
            lanes[lane * 256 + cell] += sign
    return bool(worst_truth <= t_span) and bool(worst_pred <= p_span)


@nb.njit(cache=True, nogil=True, inline="always")
def _count_window(
    truth: NDArray[np.uint16],
    pred: NDArray[np.uint16],
    start: int,
    lanes: NDArray[np.int64],
    truth_low: np.uint16,
    truth_span: np.uint16,
    pred_low: np.uint16,
    pred_span: np.uint16,
    sign: int,
) -> bool:  # pragma: no cover - compiled
    """Add ``sign`` for each of the ``WINDOW`` pairs from ``start`` to its cell,
    ``lanes[lane * 256 + t * 16 + p]``; whether they are all ``d\\n`` lines of values in range.

    Counted by runs: labels come in runs (a scan's points are in sweep order; a simulated
    scan against its prediction changes pair once in ~120 lines, the shared real scans'
    labels once in hundreds to thousands), so the window is read a span of 64 pairs at a
    time as one mask of the pairs that differ from the pair before
    (:func:`~semantic3d.core.bits.word_changes`), and each run, ended by a change, adds its
    length to its cell in one step. Only where a pair changes is it checked: every other
    pair is the same two words as the one before it, checked already. A busy span (more
    than :data:`_BUSY` changes) is checked and counted pair by pair instead.

    Counted before they are known to be valid (one pass over the text): a caller told
    False takes the window back by counting it again with ``sign`` -1 (the same steps:
    every word, valid or not, has a cell, its low nibbles). A word minus ``"0\\n"`` is the
    value exactly when it is at most 9, and the value lies in ``low..low + span`` exactly
    when it less ``low`` (wrapping) is at most ``span``. In a checked ``d\\n`` word the low
    nibble is the digit (``'0'`` is 0x30).
    """
    # a slice indexed from 0: numba then wraps no index as a negative one
    truth_window = truth[start : start + WINDOW]
    pred_window = pred[start : start + WINDOW]
    t = truth_window[0]
    p = pred_window[0]
    valid = _in_range(t, p, truth_low, truth_span, pred_low, pred_span)
    cell = ((t & 15) << 4) | (p & 15)
    run_start = 0
    for span in range(0, WINDOW, _SPAN):
        # bit j: pair span + j differs from the pair before it (the reads stay inside the
        # window: the first span's mask is read from its own first pair and moved up one)
        if span == 0:
            changes = word_changes(truth_window, pred_window, 0) << np.uint64(1)
        else:
            changes = word_changes(truth_window, pred_window, span - 1)
        if changes == 0:
            continue
        if bit_count(changes) > _BUSY:
            lanes[cell] += sign * (span - run_start)
            valid &= _count_busy_span(
                truth_window,
                pred_window,
                span,
                lanes,
                truth_low,
                truth_span,
                pred_low,
                pred_span,
                sign,
            )
            # the run after the span starts as its last pair's
            last = span + _SPAN - 1
            cell = ((truth_window[last] & 15) << 4) | (pred_window[last] & 15)
            run_start = span + _SPAN
            continue
        while changes:
            at = span + int(trailing_zeros(changes))
            changes &= changes - np.uint64(1)
            lanes[cell] += sign * (at - run_start)
            run_start = at
            t = truth_window[at]
            p = pred_window[at]
            valid &= _in_range(t, p, truth_low, truth_span, pred_low, pred_span)
            cell = ((t & 15) << 4) | (p & 15)
    lanes[cell] += sign * (WINDOW - run_start)
    return bool(valid)


@nb.njit(cache=True, nogil=True)
def _check_ranges(
    table: NDArray[np.int64], truth_low: int, truth_high: int, pred_low: int, pred_high: int
) -> None:  # pragma: no cover - compiled
    """Raise unless both value ranges lie within 0..9 and within ``table``."""
    rows, cols = table.shape
    if not (
        0 <= truth_low <= truth_high < min(rows, 10) and 0 <= pred_low <= pred_high < min(cols, 10)
    ):
        raise ValueError("pair counter: a value range outside 0..9 or the table")


@nb.njit(cache=True, nogil=True)
def _add_lanes(
    table: NDArray[np.int64],
    lanes: NDArray[np.int64],
    truth_low: int,
    truth_high: int,
    pred_low: int,
    pred_high: int,
) -> None:  # pragma: no cover - compiled
    """Add one run's lane counters (``lanes[lane * 256 + t * 16 + p]``) to ``table[t, p]``."""
    for lane in range(_LANES):
        for t in range(truth_low, truth_high + 1):
            for p in range(pred_low, pred_high + 1):
                table[t, p] += lanes[lane * 256 + t * 16 + p]


@nb.njit(cache=True, nogil=True, parallel=True)
def count_digit_pairs(
    truth: NDArray[np.uint8],
    truth_at: int,
    pred: NDArray[np.uint8],
    pred_at: int,
    n_pairs: int,
    truth_low: int,
    truth_high: int,
    pred_low: int,
    pred_high: int,
    table: NDArray[np.int64],
    n_threads: int,
) -> int:  # pragma: no cover - compiled
    """Count the ``d\\n`` line pairs at ``truth[truth_at:]`` and ``pred[pred_at:]`` into ``table``.

    At most ``n_pairs`` pairs, in whole windows. ``table[t, p]`` (indexed by label value)
    gains the pairs counted; every value counted lies in ``truth_low..truth_high`` and
    ``pred_low..pred_high`` (both within 0..9 and within the table); the windows are
    split into a run per thread of ``n_threads`` (numba's count). Returns how many
    pairs were counted: fewer than the whole windows of ``n_pairs`` when a window holds a
    line of another shape or a value out of range, the first such window not counted.
    """
    _check_ranges(table, truth_low, truth_high, pred_low, pred_high)
    n_windows = n_pairs // WINDOW
    if n_windows == 0:
        return 0
    truth_words = truth[truth_at : truth_at + 2 * WINDOW * n_windows].view(np.uint16)
    pred_words = pred[pred_at : pred_at + 2 * WINDOW * n_windows].view(np.uint16)
    runs = max(1, min(n_threads, n_windows))
    per_run = (n_windows + runs - 1) // runs
    runs = (n_windows + per_run - 1) // per_run
    counts = np.zeros((runs, _LANES * 256), dtype=np.int64)
    good = np.zeros(runs, dtype=np.int64)  # whole windows counted by each run
    t_low, t_span = np.uint16(truth_low), np.uint16(truth_high - truth_low)
    p_low, p_span = np.uint16(pred_low), np.uint16(pred_high - pred_low)
    for run in nb.prange(runs):
        lanes = np.zeros(_LANES * 256, dtype=np.int64)
        for window in range(run * per_run, min(n_windows, (run + 1) * per_run)):
            start = window * WINDOW
            if not _count_window(
                truth_words, pred_words, start, lanes, t_low, t_span, p_low, p_span, 1
            ):
                _count_window(
                    truth_words, pred_words, start, lanes, t_low, t_span, p_low, p_span, -1
                )
                break
            good[run] += 1
        counts[run] = lanes
    counted = 0
    for run in range(runs):
        _add_lanes(table, counts[run], truth_low, truth_high, pred_low, pred_high)
        counted += good[run]
        if good[run] < min(n_windows, (run + 1) * per_run) - run * per_run:
            break  # this run stopped early: later runs are not a prefix
    return counted * WINDOW


@nb.njit(cache=True, nogil=True, parallel=True)
def count_file_pairs(
    truth_fd: int,
    pred_fd: int,
    first_pair: int,
    n_pairs: int,
    truth_low: int,
    truth_high: int,
    pred_low: int,
    pred_high: int,
    table: NDArray[np.int64],
    n_threads: int,
) -> bool:  # pragma: no cover - compiled
    """Count lines ``first_pair`` to ``first_pair + n_pairs`` of two files of ``d\\n`` lines.

    Each run of ``n_threads`` (numba's count) reads its own windows of both files
    (:data:`BLOCK_WINDOWS` at a time, at offset twice the line number) and counts them as
    :func:`count_digit_pairs` does; the lines after the last whole window are checked and
    counted one by one. Returns True with ``table`` increased by the pairs when every line
    of both files is a ``d\\n`` line of a value in range (``truth_low..truth_high``,
    ``pred_low..pred_high``, within 0..9 and the table), else False with ``table``
    untouched (a read that fails or ends early too): the caller then reads the files with
    the general parsers, which report the problems.
    """
    _check_ranges(table, truth_low, truth_high, pred_low, pred_high)
    n_windows = n_pairs // WINDOW
    runs = max(1, min(n_threads, n_windows // BLOCK_WINDOWS))
    per_run = (n_windows + runs - 1) // runs
    counts = np.zeros((runs, _LANES * 256), dtype=np.int64)
    good = np.ones(runs, dtype=np.bool_)
    t_low, t_span = np.uint16(truth_low), np.uint16(truth_high - truth_low)
    p_low, p_span = np.uint16(pred_low), np.uint16(pred_high - pred_low)
    for run in nb.prange(runs):
        truth_text = np.empty(2 * WINDOW * BLOCK_WINDOWS, dtype=np.uint8)
        pred_text = np.empty(2 * WINDOW * BLOCK_WINDOWS, dtype=np.uint8)
        truth_words = truth_text.view(np.uint16)
        pred_words = pred_text.view(np.uint16)
        lanes = np.zeros(_LANES * 256, dtype=np.int64)
        window = run * per_run
        end = min(n_windows, (run + 1) * per_run)
        while window < end and good[run]:
            k = min(BLOCK_WINDOWS, end - window)
            offset = 2 * (first_pair + window * WINDOW)
            n_bytes = 2 * WINDOW * k
            if not (
                read_fully(truth_fd, truth_text, n_bytes, offset)
                and read_fully(pred_fd, pred_text, n_bytes, offset)
            ):
                good[run] = False
                break
            for j in range(k):
                if not _count_window(
                    truth_words, pred_words, j * WINDOW, lanes, t_low, t_span, p_low, p_span, 1
                ):
                    good[run] = False
                    break
            window += k
        counts[run] = lanes
    if not good.all():
        return False
    tail = n_pairs - n_windows * WINDOW
    truth_text = np.empty(2 * WINDOW, dtype=np.uint8)
    pred_text = np.empty(2 * WINDOW, dtype=np.uint8)
    offset = 2 * (first_pair + n_windows * WINDOW)
    if tail and not (
        read_fully(truth_fd, truth_text, 2 * tail, offset)
        and read_fully(pred_fd, pred_text, 2 * tail, offset)
    ):
        return False
    truth_words = truth_text.view(np.uint16)
    pred_words = pred_text.view(np.uint16)
    for k in range(tail):
        if not _in_range(truth_words[k], pred_words[k], t_low, t_span, p_low, p_span):
            return False
    for k in range(tail):
        table[truth_words[k] & 15, pred_words[k] & 15] += 1
    for run in range(runs):
        _add_lanes(table, counts[run], truth_low, truth_high, pred_low, pred_high)
    return True


def count_pairs(
    truth: NDArray[np.uint8],
    truth_at: int,
    pred: NDArray[np.uint8],
    pred_at: int,
    n_pairs: int,
    truth_range: tuple[int, int],
    pred_range: tuple[int, int],
    table: NDArray[np.int64],
) -> int:
    """:func:`count_digit_pairs` on this thread's numba threads."""
    return int(
        count_digit_pairs(
            truth,
            truth_at,
            pred,
            pred_at,
            n_pairs,
            *truth_range,
            *pred_range,
            table,
            nb.get_num_threads(),
        )
    )


def count_files(
    truth_fd: int,
    pred_fd: int,
    n_pairs: int,
    truth_range: tuple[int, int],
    pred_range: tuple[int, int],
    table: NDArray[np.int64],
    done: Callable[[int], None],
) -> bool:
    """:func:`count_file_pairs` over all ``n_pairs`` lines, on this thread's numba threads.

    In calls of :data:`FILE_PIECE_PAIRS` lines, ``done(lines counted)`` after each (the
    progress is reported, and Ctrl-C seen, between them); ``table`` gains the pairs only
    when every line counts (True).
    """
    counts = np.zeros_like(table)
    n_threads = nb.get_num_threads()
    ranges = (*truth_range, *pred_range)
    for first in range(0, n_pairs, FILE_PIECE_PAIRS):
        n = min(FILE_PIECE_PAIRS, n_pairs - first)
        if not count_file_pairs(truth_fd, pred_fd, first, n, *ranges, counts, n_threads):
            return False
        done(first + n)
    table += counts
    return True
