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

Both read a ``d\\n`` line as one 16-bit little-endian word (the byte order of every
platform numba compiles for).

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
from semantic3d.io._positioned_reads import read_fully

_WINDOW = 4096  # lines checked at once by the branch-free fast path of parse_lines
_MAX_BACKOFF = 1 << 20  # most lines parsed one by one before trying a window again


_PAIR_ZERO = 0x0A30
"""``"0\\n"`` read as one little-endian 16-bit word: ``'0'`` (0x30) low, ``'\\n'`` (0x0A) high."""


@nb.njit(cache=True, nogil=True, parallel=True)
def parse_single_digit(words: np.ndarray, out: np.ndarray) -> int:
    """Fast path for ``d\\n`` lines: fill ``out`` and return the number of malformed pairs.

    ``words`` is the block as little-endian 16-bit words, a line each; ``out`` has as many
    entries. A word minus ``"0\\n"`` is 0..9 exactly when the line is a digit and a line
    end, and its low byte is the digit byte minus ``'0'`` in any case: one subtraction and
    one comparison a line, on contiguous words (vectorised, unlike byte pairs read with a
    stride of two: 4x the rate of that loop here).
    """
    n = out.shape[0]
    bad = 0
    for i in nb.prange(n):
        value = np.uint16(words[i] - np.uint16(_PAIR_ZERO))
        out[i] = np.uint8(value & np.uint16(0xFF))
        bad += int(value > 9)
    return bad


FILE_BLOCK_LINES = 1 << 18
"""Lines :func:`read_single_digit_file` reads at a time on each thread (512 KiB of text):
the block stays in the thread's cache while it is parsed, where a block read by the
interpreter (megabytes, so that its calls are few) is written to memory and read back."""


@nb.njit(cache=True, nogil=True, parallel=True)
def read_single_digit_file(
    fd: int, first: int, out: np.ndarray, block_lines: int, n_threads: int
) -> bool:  # pragma: no cover - compiled
    """Read lines ``first..first + len(out)`` of a file of ``d\\n`` lines into ``out``.

    The lines are split into one run of whole blocks per thread of ``n_threads`` (numba's
    count); each run reads its blocks of ``block_lines`` lines (:data:`FILE_BLOCK_LINES`
    in use) with ``pread`` into a buffer of its own (at offset twice the line number) and
    converts them as :func:`parse_single_digit` does, into its slice of ``out`` (so the
    slice is first touched by the thread that fills it). True when every line is a
    ``d\\n`` line; False at a line of another shape, or a read that fails or ends early
    (``out`` then holds anything): the caller reads the file with the checking parser.
    """
    n = out.shape[0]
    n_blocks = (n + block_lines - 1) // block_lines
    runs = max(1, min(n_threads, n_blocks))
    per_run = (n_blocks + runs - 1) // runs
    good = np.ones(runs, dtype=np.bool_)
    for run in nb.prange(runs):
        text = np.empty(2 * min(n, block_lines), dtype=np.uint8)
        words = text.view(np.uint16)
        for block in range(run * per_run, min(n_blocks, (run + 1) * per_run)):
            start = block * block_lines
            lines = min(n - start, block_lines)
            if not read_fully(fd, text, 2 * lines, 2 * (first + start)):
                good[run] = False
                break
            # slices indexed from 0, so numba wraps no index as a negative one
            # (that check per line kept the loop scalar)
            block_out = out[start : start + lines]
            bad = False
            for k in range(lines):
                value = np.uint16(words[k] - np.uint16(_PAIR_ZERO))
                block_out[k] = np.uint8(value & np.uint16(0xFF))
                bad |= bool(value > 9)
            if bad:
                good[run] = False
                break
    return bool(good.all())


@nb.njit(cache=True, nogil=True)
def _parse_window(
    buf: np.ndarray, i: int, out: np.ndarray, n: int, lowest: np.uint8, span: np.uint8
) -> bool:  # pragma: no cover - compiled
    """Parse ``_WINDOW`` ``d\n`` lines at ``buf[i]`` into ``out[n]``; False if any is not.

    Each line read as one 16-bit word, as :func:`parse_single_digit` does (from any
    address: ``i`` may be odd); the word minus ``"0\\n"`` is the digit, and the line is one
    of ``lowest..lowest + span`` exactly when that difference less ``lowest`` is at most
    ``span``. Branch-free, so LLVM vectorises it (2.5x the rate of byte pairs read with a
    stride of two); a function of its own because inlined into :func:`parse_lines` it
    slows that function's per-line loops by a third.
    """
    words = buf[i : i + 2 * _WINDOW].view(np.uint16)
    bad = False
    for k in range(_WINDOW):
        digit = np.uint16(words[k] - np.uint16(_PAIR_ZERO))
        out[n + k] = np.uint8(digit & np.uint16(0xFF))
        bad |= bool(np.uint16(digit - lowest) > span)
    return not bad


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
