"""Compiled kernels for ``.labels`` text: one non-negative integer per line.

Hand-written because this is the benchmark's hottest path: a submission holds ~4 billion
labels, and general CSV parsers (polars, pyarrow) manage < 100 M labels/s here while a
byte loop reaches several hundred million.

Two parsers, one format:

- :func:`parse_single_digit`: whole blocks of ``d\n`` lines (the benchmark's files),
  split over all cores; it only says whether the block had that shape.
- :func:`parse_lines`: every accepted shape (CRLF, blanks, several digits, a missing
  final newline), resumable across the blocks of a stream, checking each value against
  a range. It never stops at a problem: it counts bad lines and records the first of
  each kind in ``state`` / ``text`` (slots below), so one pass finds every problem.
  :class:`semantic3d.io.labelstream.LabelStream` drives it over any binary stream (files,
  zip members), and :mod:`semantic3d.io.labels` falls back to it for blocks the fast
  path rejects.

Small texts do not come here: :mod:`semantic3d.io._label_parsing` parses them with numpy
(same results) and imports this module only for long ones, since loading numba costs
more than parsing a small file.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from semantic3d.io._label_grammar import (  # one definition for both parsers
    LINES,
    N_RANGE,
    N_SYNTAX,
    RANGE_LINE,
    RANGE_VALUE,
    SYNTAX_LINE,
    TEXT_BYTES,
    TEXT_LEN,
    VALUE_CAP,
)

_WINDOW = 4096  # lines checked at once by the branch-free fast path of parse_lines
_MAX_BACKOFF = 1 << 20  # most lines parsed one by one before trying a window again


@nb.njit(cache=True, nogil=True, parallel=True)
def parse_single_digit(block: np.ndarray, out: np.ndarray) -> int:
    """Fast path for ``d\\n`` lines: fill ``out`` and return the number of malformed pairs.

    ``block`` has an even length; ``out`` has ``len(block) // 2`` entries.
    """
    n = out.shape[0]
    bad = 0
    for i in nb.prange(n):
        digit = np.uint8(block[2 * i] - 48)
        out[i] = digit
        bad += (digit > 9) | (block[2 * i + 1] != 10)
    return bad


@nb.njit(cache=True, nogil=True)
def _parse_window(
    buf: np.ndarray, i: int, out: np.ndarray, n: int, lowest: np.uint8, span: np.uint8
) -> bool:  # pragma: no cover - compiled
    """Parse ``_WINDOW`` ``d\n`` lines at ``buf[i]`` into ``out[n]``; False if any is not.

    Branch-free, so LLVM vectorises it; a function of its own because inlined into
    :func:`parse_lines` it slows that function's per-line loops by a third.
    """
    bad = 0
    for k in range(_WINDOW):
        digit = np.uint8(buf[i + 2 * k] - 48)
        out[n + k] = digit
        bad |= (np.uint8(digit - lowest) > span) | (buf[i + 2 * k + 1] != 10)
    return bad == 0


@nb.njit(cache=True, nogil=True, inline="always")
def _count_out_of_range(state: np.ndarray, line: int, value: int) -> None:
    if state[N_RANGE] == 0:
        state[RANGE_LINE] = line
        state[RANGE_VALUE] = value
    state[N_RANGE] += 1


@nb.njit(cache=True, nogil=True)
def parse_lines(
    buf: np.ndarray,
    start: int,
    end: int,
    final: bool,
    out: np.ndarray,
    filled: int,
    capacity: int,
    low: int,
    high: int,
    state: np.ndarray,
    text: np.ndarray,
) -> tuple[int, int]:  # pragma: no cover - compiled
    """Parse the lines of ``buf[start:end]`` into ``out[filled:capacity]``.

    Returns ``(position, filled)``: where parsing stopped (``out`` full, or the start of
    an incomplete last line when ``final`` is false) and how many values ``out`` holds.
    Every line gives one value; a line that is not an integer, or whose value is outside
    ``low..high``, gives 0 and is counted in ``state`` (the first of each kind recorded).
    """
    # Hand-written hot path. Benchmark files hold one digit a line, so whole windows of
    # "d\n" pairs are parsed and checked without branches (LLVM vectorises the loop, ~3x
    # a per-line loop). A window holding anything else is re-parsed line by line, and
    # windows are tried again after exponentially more lines, so files of another shape
    # (CRLF, several digits) do not pay for them. Line by line: a fast path for lines of
    # one to three digits and a line end, then one checking pass over the line.
    i = start
    n = filled
    line = state[LINES]
    # A window accepts single digits in low..min(high, 9); none when that is empty.
    windowed = 0 <= low <= min(high, 9)
    lowest = np.uint8(low) if windowed else np.uint8(0)
    span = np.uint8(min(high, 9) - low) if windowed else np.uint8(0)
    slow = 0  # lines left to parse one by one before trying a window again
    backoff = _WINDOW
    while n < capacity:
        if windowed and slow == 0 and n + _WINDOW <= capacity and i + 2 * _WINDOW <= end:
            if _parse_window(buf, i, out, n, lowest, span):
                n += _WINDOW
                i += 2 * _WINDOW
                line += _WINDOW
                backoff = _WINDOW
                continue
            slow = backoff
            backoff = min(2 * backoff, _MAX_BACKOFF)
        if slow > 0:
            slow -= 1
        if i + 4 < end:  # room for "ddd\r\n": no bounds checks below
            c = buf[i]
            if 48 <= c <= 57:
                value = c - 48
                k = i + 1
                c = buf[k]
                if 48 <= c <= 57:
                    value = value * 10 + (c - 48)
                    k += 1
                    c = buf[k]
                    if 48 <= c <= 57:
                        value = value * 10 + (c - 48)
                        k += 1
                        c = buf[k]
                if c == 10:
                    step = k + 1 - i
                elif c == 13 and buf[k + 1] == 10:
                    step = k + 2 - i
                else:
                    step = 0
                if step:
                    line += 1
                    if value < low or value > high:
                        _count_out_of_range(state, line, value)
                        value = 0
                    out[n] = value
                    n += 1
                    i += step
                    continue
        if i >= end:
            break
        # One pass: blanks, digits, blanks or CR, then the line end.
        j = i
        while j < end and (buf[j] == 32 or buf[j] == 9):
            j += 1
        value = 0
        n_digits = 0
        while j < end and 48 <= buf[j] <= 57:
            if value < VALUE_CAP:
                value = value * 10 + (buf[j] - 48)
            n_digits += 1
            j += 1
        while j < end and (buf[j] == 32 or buf[j] == 9 or buf[j] == 13):
            j += 1
        ok = n_digits > 0 and (j == end or buf[j] == 10)
        while j < end and buf[j] != 10:  # a bad line: find its end
            j += 1
        if j == end and not final:
            break  # incomplete line: wait for more bytes
        line += 1
        if not ok:
            if state[N_SYNTAX] == 0:
                state[SYNTAX_LINE] = line
                m = min(j - i, TEXT_BYTES)
                for k in range(m):
                    text[k] = buf[i + k]
                state[TEXT_LEN] = m
            state[N_SYNTAX] += 1
            value = 0
        elif value < low or value > high:
            _count_out_of_range(state, line, value)
            value = 0
        out[n] = value
        n += 1
        i = j + 1 if j < end else end
    state[LINES] = line
    return i, n


@nb.njit(cache=True, nogil=True)
def format_labels(labels: np.ndarray, out: np.ndarray) -> int:
    """Write ``labels`` (uint8) as decimal lines into ``out``; return the bytes used.

    ``out`` needs ``4 * len(labels)`` bytes.
    """
    pos = 0
    for i in range(labels.shape[0]):
        value = labels[i]
        if value >= 100:
            out[pos] = 48 + value // 100
            pos += 1
        if value >= 10:
            out[pos] = 48 + (value // 10) % 10
            pos += 1
        out[pos] = 48 + value % 10
        out[pos + 1] = 10
        pos += 2
    return pos
