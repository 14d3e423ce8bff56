"""``.labels`` parsing without numba, and the choice between it and the compiled kernels.

Importing numba and loading its cached kernels costs about a CPU-second, far more than
parsing a small file: a ten-scan submission of test files, or the labels of a scan of a
few thousand points. Texts up to :data:`SMALL_TEXT_BYTES` are therefore parsed here with
numpy (whole lines classified at once, Python only for lines of an unusual shape), and
longer ones by :mod:`semantic3d.io._label_kernels`, imported on first use. Both give the
same values, the same ``state`` and ``text`` and the same return values for the same
input (``tests/io/test_label_parsing.py`` checks it with hypothesis), so which one ran is
invisible to callers.
"""

from __future__ import annotations

import re
from typing import Any

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
)

SMALL_TEXT_BYTES = 1 << 20
"""Texts up to this size are parsed with numpy; longer ones by the compiled kernels."""
_SMALL_IRREGULAR_LINES = 1 << 15
"""Lines of an unusual shape parsed in Python per call; more go to the kernels."""

_LINE = re.compile(rb"[ \t]*([0-9]+)[ \t\r]*")


def _kernels() -> Any:
    from semantic3d.io import _label_kernels

    return _label_kernels


def _use_numpy(n_bytes: int) -> bool:
    return n_bytes <= SMALL_TEXT_BYTES


def parse_single_digit(block: np.ndarray, out: np.ndarray) -> int:
    """Fill ``out`` from ``d\\n`` lines; the number of malformed pairs (0: the block had that shape).

    ``block`` has an even length; ``out`` has ``len(block) // 2`` entries.
    """
    if not _use_numpy(block.size):
        words = np.ascontiguousarray(block).view(np.uint16)  # a line a word
        return int(_kernels().parse_single_digit(words, out))
    digits = block[0::2] - np.uint8(48)
    out[:] = digits
    return int(np.count_nonzero((digits > 9) | (block[1::2] != 10)))


def read_single_digit_file(fd: int, first: int, out: np.ndarray, *, block_lines: int = 0) -> bool:
    """Read lines ``first..first + len(out)`` of the file ``fd`` (``d\\n`` lines, read with
    ``pread``: the caller checks ``os.pread``) into ``out`` on this thread's numba threads;
    whether every line had that shape (else ``out`` holds anything). ``block_lines``: the
    lines each thread reads at a time (default the kernel's)."""
    import numba

    kernels = _kernels()
    lines = block_lines or kernels.FILE_BLOCK_LINES
    return bool(kernels.read_single_digit_file(fd, first, out, lines, numba.get_num_threads()))


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
) -> tuple[int, int]:
    """Parse the lines of ``buf[start:end]`` into ``out[filled:capacity]``.

    Returns ``(position, filled)``: where parsing stopped (``out`` full, or the start of
    an incomplete last line when ``final`` is false) and how many values ``out`` holds.
    Every line gives one value; a line that is not an integer, or whose value is outside
    ``low..high``, gives 0 and is counted in ``state`` (the first of each kind recorded).
    Accepted: blanks, digits, then blanks or carriage returns before the line end.
    """
    if _use_numpy(end - start):
        done = _parse_lines_numpy(
            buf, start, end, final, out, filled, capacity, low, high, state, text
        )
        if done is not None:
            return done
    position, n = _kernels().parse_lines(
        buf, start, end, final, out, filled, capacity, low, high, state, text
    )
    return int(position), int(n)


def _line_ends(region: np.ndarray, wanted: int) -> np.ndarray:
    """Offsets of the first ``wanted`` newlines of ``region`` (all, when fewer).

    Looks at a prefix a few bytes a line long first, so a call that parses a few lines
    of a long text does not scan all of it.
    """
    prefix = min(region.size, 4 * wanted + 64)
    ends = np.flatnonzero(region[:prefix] == 10)
    if ends.size < wanted and prefix < region.size:
        ends = np.flatnonzero(region == 10)
    return ends[:wanted]


def _parse_lines_numpy(
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
) -> tuple[int, int] | None:
    """:func:`parse_lines` with numpy; None when too many lines need Python (use the kernel)."""
    room = capacity - filled
    if room <= 0 or end <= start:
        return start, filled
    region = buf[start:end]
    ends = _line_ends(region, room)
    if ends.size < room and final and (ends.size == 0 or ends[-1] != region.size - 1):
        ends = np.append(ends, region.size)  # the last line, without a line end
    n_lines = ends.size
    if n_lines == 0:
        return start, filled
    starts = np.empty(n_lines, np.int64)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    lengths = ends - starts
    # The benchmark's shapes, "d\n" and "d\r\n", are classified at once; others in Python.
    first = region[np.minimum(starts, region.size - 1)]
    second = region[np.minimum(starts + 1, region.size - 1)]
    values = (first - np.uint8(48)).astype(np.int64)
    regular = (values <= 9) & ((lengths == 1) | ((lengths == 2) & (second == 13)))
    irregular = np.flatnonzero(~regular)
    if irregular.size > _SMALL_IRREGULAR_LINES:
        return None
    syntax = np.zeros(n_lines, bool)
    for index in irregular.tolist():
        raw = bytes(region[starts[index] : ends[index]])
        match = _LINE.fullmatch(raw)
        if match is None:
            syntax[index] = True
            values[index] = 0
        else:
            digits = match.group(1).lstrip(b"0")[:16]  # the kernel stops past VALUE_CAP
            values[index] = int(digits) if digits else 0
    out_of_range = ~syntax & ((values < low) | (values > high))
    line = int(state[LINES])
    if syntax.any():
        if state[N_SYNTAX] == 0:
            index = int(np.argmax(syntax))
            state[SYNTAX_LINE] = line + index + 1
            shown = region[starts[index] : starts[index] + min(lengths[index], TEXT_BYTES)]
            text[: shown.size] = shown
            state[TEXT_LEN] = shown.size
        state[N_SYNTAX] += int(np.count_nonzero(syntax))
    if out_of_range.any():
        if state[N_RANGE] == 0:
            index = int(np.argmax(out_of_range))
            state[RANGE_LINE] = line + index + 1
            state[RANGE_VALUE] = values[index]
        state[N_RANGE] += int(np.count_nonzero(out_of_range))
    values[syntax | out_of_range] = 0
    out[filled : filled + n_lines] = values
    state[LINES] = line + n_lines
    position = start + min(int(ends[-1]) + 1, region.size)
    return position, filled + n_lines
