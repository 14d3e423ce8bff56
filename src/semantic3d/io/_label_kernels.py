"""Compiled kernels for ``.labels`` text: one non-negative integer per line.

Hand-written because this is the benchmark's hottest path: a submission holds ~4 billion
labels, and general CSV parsers (polars, pyarrow) manage < 100 M labels/s here while a
byte loop reaches several hundred million. Kernels return status codes; the Python side
turns a code into a message with the file name and line number.
"""

from __future__ import annotations

import numba as nb
import numpy as np

OK = 0
EMPTY_LINE = 1
NOT_AN_INTEGER = 2
OUT_OF_RANGE = 3


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
def parse_general(block: np.ndarray, out: np.ndarray, max_value: int) -> tuple[int, int, int]:
    """Parse any block of whole lines: blanks around the number and ``\\r`` are tolerated.

    Returns ``(n_lines, status, bad_line)``; ``bad_line`` is the 0-based line of the first
    problem when ``status`` is not :data:`OK`. ``out`` must hold one entry per line.
    """
    n_bytes = block.shape[0]
    line = 0
    pos = 0
    while pos < n_bytes:
        c = block[pos]
        while c == 32 or c == 9:
            pos += 1
            c = block[pos]
        if c == 10 or (c == 13 and block[pos + 1] == 10):
            return line, EMPTY_LINE, line
        value = 0
        n_digits = 0
        while c >= 48 and c <= 57:
            if value <= max_value:
                value = value * 10 + (c - 48)
            n_digits += 1
            pos += 1
            c = block[pos]
        while c == 32 or c == 9 or c == 13:
            pos += 1
            c = block[pos]
        if n_digits == 0 or c != 10:
            return line, NOT_AN_INTEGER, line
        if value > max_value:
            return line, OUT_OF_RANGE, line
        out[line] = value
        line += 1
        pos += 1
    return line, OK, -1


@nb.njit(cache=True, nogil=True)
def count_newlines(block: np.ndarray) -> int:
    """Number of ``\\n`` bytes in ``block``."""
    total = 0
    for i in range(block.shape[0]):
        total += block[i] == 10
    return total


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
