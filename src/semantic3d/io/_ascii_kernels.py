"""Compiled kernels for Semantic3D point text: ``x y z intensity r g b`` per line.

Hand-written because this is the hottest IO path (scans of ~500 M lines, 17 GB) and the
general CSV readers (pyarrow, pandas) spend most of their time on what this format does
not need: quoting, type inference, arbitrary widths. The benchmark's numbers have a few
fixed shapes (``-12.345``, ``-1515``, ``255``), so a token is read eight bytes at a time
(SWAR: one unaligned load, a bit trick for the first non-digit, three multiplies for the
digits) rather than byte by byte with a branch per character.

Exactness. A token's digits form an integer mantissa ``m`` and a decimal exponent ``e``.
When ``m`` has at most 15 significant digits (so ``m < 2**53`` is an exact double) and
``|e| <= 22`` (so ``10**|e|`` is an exact double), ``m * 10**e`` or ``m / 10**-e`` is one
IEEE operation on exact operands, hence correctly rounded: the same double as Python's
``float()``. Every other syntactically valid token (16+ significant digits, large
exponents) is *deferred*: its position is recorded and the caller converts it with a
correctly rounded general algorithm (numpy's, which is CPython's ``dtoa``). Nothing is
approximated.

Work split (driven by :mod:`semantic3d.io._point_reader`): one call of
:func:`parse_window` cuts a window of whole lines at newlines into segments
(:func:`line_start`), counts the lines of each (:func:`count_lines`, vectorised) and
parses every segment on its own thread straight into the output arrays at its row
offset: no copy, no Python per line or per segment (a thread pool fed from Python spent
more time handing segments out than parsing them on 16 cores). The kernels release the
GIL and run on numba's threads (the package's thread budget).

What bounds it: instructions, not memory. A benchmark line (~37 bytes) costs ~400
instructions (~75 per coordinate, ~35 per integer, the line checks), ~5 cycles a byte on
this machine's cores, while the page cache delivers several GB/s. Getting within a few
times of ``cat`` would take SIMD structural indexing (classify 32 bytes per instruction,
convert tokens with byte shuffles), which numba does not express.

Small files do not come here: :mod:`semantic3d.io._point_text` parses them in Python with
the same grammar and results, since loading numba costs more than parsing them.
"""

from __future__ import annotations

from typing import Any

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from semantic3d.core.atomic import take_next
from semantic3d.core.bits import trailing_zeros
from semantic3d.io._page_advice import DROP_ADVICE, advise
from semantic3d.io._point_text import (  # problem codes: one definition for both parsers
    BAD_NUMBER,
    COLUMN_COUNT,
    N_COLUMNS,
    NOT_INTEGER,
    OK,
    OUT_OF_RANGE,
    SLOW_FULL,
)

FAST_MARGIN = 160
"""The SWAR path reads up to this many bytes past a line start (7 tokens of at most 19
bytes); closer to the end of the readable buffer the byte-by-byte path runs."""

# Segment state columns (one row per segment): parse_segment's results and the end.
STATE_STATUS, STATE_POS, STATE_ROW, STATE_SLOW, STATE_END = range(5)
STATE_SIZE = 5
# Deferred-token columns.
SLOW_START, SLOW_STOP, SLOW_ROW, SLOW_COLUMN = range(4)

_POW10 = np.array([10.0**i for i in range(23)], dtype=np.float64)
_POW10_INT = np.array([10**i for i in range(19)], dtype=np.uint64)
_ZEROS = np.uint64(0x3030303030303030)
_LOW7 = np.uint64(0x7F7F7F7F7F7F7F7F)
_PLUS_118 = np.uint64(0x7676767676767676)
_HIGH_BITS = np.uint64(0x8080808080808080)
_NIBBLES = np.uint64(0x0F0F0F0F0F0F0F0F)
_BYTE_PAIRS = np.uint64(0x00FF00FF00FF00FF)
_WORD_PAIRS = np.uint64(0x0000FFFF0000FFFF)
_MUL_1 = np.uint64(10 * 256 + 1)
_MUL_2 = np.uint64(100 * 65536 + 1)
_MUL_3 = np.uint64(10000 * (1 << 32) + 1)
_U8 = np.uint64(8)
_U16 = np.uint64(16)
_U32 = np.uint64(32)
_U63 = np.uint64(63)
_U1 = np.uint64(1)
_DIGIT_CAP = 19  # digits accumulated into the mantissa (10**19 < 2**64)
_EXACT_DIGITS = 15  # significant digits below 2**53
_EXACT_EXPONENT = 22  # 10**22 is the largest exact power of ten in float64
_EXPONENT_CAP = 100_000


def _load_u64_intrinsic(typingctx, array, index):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Eight bytes of a uint8 array from ``index``, little-endian, unaligned, unchecked."""
    if not (isinstance(array, types.Array) and array.dtype == types.uint8):
        return None
    if not isinstance(index, types.Integer):
        return None
    signature = types.uint64(array, index)

    def codegen(context, builder, sig, args):  # type: ignore[no-untyped-def]
        data = context.make_array(sig.args[0])(context, builder, args[0]).data
        offset = context.cast(builder, args[1], sig.args[1], types.intp)
        pointer = builder.bitcast(builder.gep(data, [offset]), ir.IntType(64).as_pointer())
        return builder.load(pointer, align=1)

    return signature, codegen


def _byte_intrinsic(typingctx, array, index):  # type: ignore[no-untyped-def]  # pragma: no cover
    """``array[index]`` for a uint8 array without the negative-index wraparound."""
    if not (isinstance(array, types.Array) and array.dtype == types.uint8):
        return None
    if not isinstance(index, types.Integer):
        return None
    signature = types.int64(array, index)

    def codegen(context, builder, sig, args):  # type: ignore[no-untyped-def]
        data = context.make_array(sig.args[0])(context, builder, args[0]).data
        offset = context.cast(builder, args[1], sig.args[1], types.intp)
        return builder.zext(builder.load(builder.gep(data, [offset])), ir.IntType(64))

    return signature, codegen


_load_u64: Any = intrinsic(_load_u64_intrinsic)
_byte: Any = intrinsic(_byte_intrinsic)


@nb.njit(cache=True, nogil=True, inline="always")
def _is_delimiter(c: Any) -> Any:  # pragma: no cover - compiled
    return (c == 32) | (c == 9) | (c == 10) | (c == 13)


@nb.njit(cache=True, nogil=True, inline="always")
def _digits_of(word: Any) -> tuple[Any, Any]:  # pragma: no cover - compiled
    """Leading decimal digits of 8 text bytes (little-endian word): ``(count, value)``.

    ``count`` is 8 when all eight are digits (the value is then unusable). No branch:
    bytes are xored with ``'0'``, digits become 0..9, and a byte is a non-digit when its
    low 7 bits plus 118 reach 128 or its top bit is set.
    """
    x = word ^ _ZEROS
    non_digit = (((x & _LOW7) + _PLUS_118) | x) & _HIGH_BITS
    count = trailing_zeros(non_digit) >> np.uint64(3)
    # Shift the digits to the top (the bytes past them fall out; zeros enter as leading
    # zeros), then combine pairs, quads and octets: 8 digits in three multiplies.
    shift = (np.uint64(63) - (count << np.uint64(3))) & _U63
    x = (x << shift) << _U1
    x = ((x & _NIBBLES) * _MUL_1) >> _U8
    x = ((x & _BYTE_PAIRS) * _MUL_2) >> _U16
    x = ((x & _WORD_PAIRS) * _MUL_3) >> _U32
    return np.int64(count), x


@nb.njit(cache=True, nogil=True, inline="always")
def _byte_of(word: Any, index: Any) -> Any:  # pragma: no cover - compiled
    """Byte ``index`` (0..7) of a little-endian word."""
    return np.int64((word >> (np.uint64(index << 3) & _U63)) & np.uint64(0xFF))


@nb.njit(cache=True, nogil=True, inline="always")
def _signed_word(buf: np.ndarray, pos: int) -> tuple[bool, int, np.uint64]:  # pragma: no cover
    """``(negative, digits_start, word at digits_start)`` with one load: a leading ``-`` is
    shifted out of the word (a zero byte, a non-digit, enters at the top)."""
    word = _load_u64(buf, pos)
    negative = (word & np.uint64(0xFF)) == np.uint64(45)
    return negative, pos + negative, (word >> _U8) if negative else word


@nb.njit(cache=True, nogil=True, inline="always")
def _fast_decimal(buf: np.ndarray, pos: Any) -> tuple[Any, Any, Any]:  # pragma: no cover
    """A decimal of at most 7 digits and 8 bytes after its sign (``-12.345``, ``870.25``):
    ``(value, end, ok)``; longer shapes go to :func:`_wide_decimal`.

    One load: the point, when there is one, is squeezed out of the word (the bytes after
    it move down one place), leaving the digits of ``mantissa`` contiguous for a single
    SWAR conversion; the number of digits after the point is the scale.
    """
    negative, start, word = _signed_word(buf, pos)
    n_whole, _ = _digits_of(word)
    has_point = _byte_of(word, n_whole) == 46
    low = (_U1 << (np.uint64(n_whole << 3) & _U63)) - _U1
    squeezed = (word & low) | ((word >> _U8) & ~low)
    n_digits, mantissa = _digits_of(squeezed if has_point else word)
    n_fraction = n_digits - n_whole if has_point else 0
    end = start + n_digits + has_point
    ok = (n_digits > 0) & (n_digits < 8) & (n_whole < 8) & _is_delimiter(_byte(buf, end))
    if not ok:
        return _wide_decimal(buf, pos)
    value = float(np.int64(mantissa)) / _POW10[n_fraction & 7]
    return (-value if negative else value), end, ok


@nb.njit(cache=True, nogil=True)
def _wide_decimal(buf: np.ndarray, pos: Any) -> tuple[Any, Any, Any]:  # pragma: no cover
    """``[-]d{0,7}[.d{0,7}]`` then a delimiter: ``(value, end, ok)``; ok False for any other shape.

    Branch-free: the fraction is scanned whether or not there is a point, and selected.
    Reads at most 17 bytes from ``pos``.
    """
    negative, start, word = _signed_word(buf, pos)
    n_whole, whole = _digits_of(word)
    point = start + n_whole
    n_after, after = _digits_of(_load_u64(buf, point + 1))
    has_point = _byte_of(word, n_whole) == 46
    n_fraction = n_after if has_point else 0
    fraction = after if has_point else np.uint64(0)
    end = point + (1 + n_fraction if has_point else 0)
    mantissa = np.int64(whole * _POW10_INT[n_fraction & 7] + fraction)
    ok = (n_whole < 8) & (n_fraction < 8) & (n_whole + n_fraction > 0)
    ok = ok & _is_delimiter(_byte(buf, end))
    value = float(mantissa) / _POW10[n_fraction & 7]
    return (-value if negative else value), end, ok


@nb.njit(cache=True, nogil=True, inline="always")
def _fast_integer(buf: np.ndarray, pos: Any) -> tuple[Any, Any, Any]:  # pragma: no cover
    """``[-]d{1,7}``: ``(value, end, ok)``. Reads at most 8 bytes from ``pos``.

    ``ok`` says only that 1 to 7 digits were found: the caller checks the byte at ``end``
    (:func:`_fast_line` wants a blank or the line end there, which no digit is).
    """
    negative, start, word = _signed_word(buf, pos)
    n_digits, digits = _digits_of(word)
    value = np.int64(digits)
    return (-value if negative else value), start + n_digits, (n_digits > 0) & (n_digits < 8)


@nb.njit(cache=True, nogil=True, inline="always")
def _fast_unsigned(buf: np.ndarray, pos: Any) -> tuple[Any, Any, Any]:  # pragma: no cover
    """``d{1,7}``, for a colour: ``(value, end, ok)``, as :func:`_fast_integer` without the
    sign. A sign is not a digit (not ok): such a line goes to the general path, which
    accepts ``-0`` and reports any other negative colour, as it did when this path took
    the sign and refused the negative value."""
    n_digits, digits = _digits_of(_load_u64(buf, pos))
    return np.int64(digits), pos + n_digits, (n_digits > 0) & (n_digits < 8)


@nb.njit(cache=True, nogil=True, inline="always")
def _fast_line(
    buf: np.ndarray, pos: int, row: int, xyz: np.ndarray, intensity: np.ndarray, rgb: np.ndarray
) -> int:  # pragma: no cover - compiled
    """The benchmark's line shape, single blanks, ``\n`` or ``\r\n``: the next line's
    offset, or -1 (nothing stored) for any other shape. One branch per line; reads at
    most ``FAST_MARGIN`` bytes from ``pos``."""
    x, p, ok = _fast_decimal(buf, pos)
    ok = ok & (_byte(buf, p) == 32)
    y, p, ok1 = _fast_decimal(buf, p + 1)
    ok = ok & ok1 & (_byte(buf, p) == 32)
    z, p, ok1 = _fast_decimal(buf, p + 1)
    ok = ok & ok1 & (_byte(buf, p) == 32)
    i, p, ok1 = _fast_integer(buf, p + 1)
    ok = ok & ok1 & (_byte(buf, p) == 32)
    r, p, ok1 = _fast_unsigned(buf, p + 1)
    ok = ok & ok1 & (_byte(buf, p) == 32)
    g, p, ok1 = _fast_unsigned(buf, p + 1)
    ok = ok & ok1 & (_byte(buf, p) == 32)
    b, p, ok1 = _fast_unsigned(buf, p + 1)
    p += _byte(buf, p) == 13
    ok = ok & ok1 & (_byte(buf, p) == 10)
    ok = ok & ((r | g | b) <= 255)
    if not ok:
        return -1
    xyz[row, 0] = x
    xyz[row, 1] = y
    xyz[row, 2] = z
    intensity[row] = i
    rgb[row, 0] = r
    rgb[row, 1] = g
    rgb[row, 2] = b
    return p + 1


@nb.njit(cache=True, nogil=True)
def parse_token(buf: np.ndarray, pos: int) -> tuple[int, float, int]:  # pragma: no cover
    """The general, byte-by-byte number scanner: ``(kind, value, end)``.

    ``kind`` is OK (``value`` is exact), BAD_NUMBER (not ``[+-]digits[.digits][e[+-]digits]``
    followed by a delimiter) or SLOW_FULL (valid, but the value needs the general
    algorithm: more than 15 significant digits or a decimal exponent beyond ±22).
    """
    c = buf[pos]
    negative = False
    if c == 45 or c == 43:
        negative = c == 45
        pos += 1
        c = buf[pos]
    mantissa = np.uint64(0)
    n_significant = 0
    n_digits = 0
    exponent = 0
    while 48 <= c <= 57:
        if mantissa != 0 or c != 48:
            if n_significant < _DIGIT_CAP:
                mantissa = mantissa * np.uint64(10) + np.uint64(c - 48)
            else:
                exponent += 1
            n_significant += 1
        n_digits += 1
        pos += 1
        c = buf[pos]
    if c == 46:
        pos += 1
        c = buf[pos]
        while 48 <= c <= 57:
            if mantissa != 0 or c != 48:
                if n_significant < _DIGIT_CAP:
                    mantissa = mantissa * np.uint64(10) + np.uint64(c - 48)
                    exponent -= 1
                n_significant += 1
            else:
                exponent -= 1
            n_digits += 1
            pos += 1
            c = buf[pos]
    if n_digits == 0:
        return BAD_NUMBER, 0.0, pos
    if c == 101 or c == 69:
        pos += 1
        c = buf[pos]
        exponent_negative = False
        if c == 45 or c == 43:
            exponent_negative = c == 45
            pos += 1
            c = buf[pos]
        written = 0
        n_exponent_digits = 0
        while 48 <= c <= 57:
            if written < _EXPONENT_CAP:
                written = written * 10 + (c - 48)
            n_exponent_digits += 1
            pos += 1
            c = buf[pos]
        if n_exponent_digits == 0:
            return BAD_NUMBER, 0.0, pos
        exponent += -written if exponent_negative else written
    if not _is_delimiter(c):
        return BAD_NUMBER, 0.0, pos
    if mantissa == 0:
        value = 0.0
    elif n_significant > _EXACT_DIGITS or not -_EXACT_EXPONENT <= exponent <= _EXACT_EXPONENT:
        return SLOW_FULL, 0.0, pos
    elif exponent < 0:
        value = float(mantissa) / _POW10[-exponent]
    else:
        value = float(mantissa) * _POW10[exponent]
    return OK, (-value if negative else value), pos


@nb.njit(cache=True, nogil=True, inline="always")
def _store_integer(
    column: int, value: float, row: int, intensity: np.ndarray, rgb: np.ndarray
) -> int:  # pragma: no cover - compiled
    if value != np.floor(value):
        return NOT_INTEGER
    if column == 3:
        if value < -2147483648.0 or value > 2147483647.0:
            return OUT_OF_RANGE
        intensity[row] = np.int32(value)
    else:
        if value < 0.0 or value > 255.0:
            return OUT_OF_RANGE
        rgb[row, column - 4] = np.uint8(value)
    return OK


@nb.njit(cache=True, nogil=True)
def _general_line(
    buf: np.ndarray,
    pos: int,
    row: int,
    xyz: np.ndarray,
    intensity: np.ndarray,
    rgb: np.ndarray,
    slow: np.ndarray,
    n_slow: int,
) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """Any accepted line shape, token by token: ``(status, next line or this line's start,
    n_slow)``. Tokens needing the general float algorithm are appended to ``slow``."""
    line_start = pos
    line_slow = n_slow
    for column in range(N_COLUMNS):
        c = buf[pos]
        while c == 32 or c == 9:
            pos += 1
            c = buf[pos]
        if c == 10 or c == 13:
            return COLUMN_COUNT, line_start, line_slow
        kind, value, stop = parse_token(buf, pos)
        if kind == BAD_NUMBER:
            return BAD_NUMBER, line_start, line_slow
        if kind == SLOW_FULL:
            if n_slow == slow.shape[0]:
                return SLOW_FULL, line_start, line_slow
            slow[n_slow, SLOW_START] = pos
            slow[n_slow, SLOW_STOP] = stop
            slow[n_slow, SLOW_ROW] = row
            slow[n_slow, SLOW_COLUMN] = column
            n_slow += 1
        elif column < 3:
            xyz[row, column] = value
        else:
            status = _store_integer(column, value, row, intensity, rgb)
            if status != OK:
                return status, line_start, line_slow
        pos = stop
    c = buf[pos]
    while c == 32 or c == 9 or c == 13:
        pos += 1
        c = buf[pos]
    if c != 10:
        return COLUMN_COUNT, line_start, line_slow
    return OK, pos + 1, n_slow


@nb.njit(cache=True, nogil=True)
def _run(
    buf: np.ndarray,
    readable: int,
    pos: int,
    end: int,
    row: int,
    xyz: np.ndarray,
    intensity: np.ndarray,
    rgb: np.ndarray,
    slow: np.ndarray,
    n_slow: int,
) -> tuple[int, int, int, int]:  # pragma: no cover - compiled
    while pos < end:
        if pos + FAST_MARGIN <= readable:
            next_line = _fast_line(buf, pos, row, xyz, intensity, rgb)
            if next_line >= 0:
                pos = next_line
                row += 1
                continue
        status, next_line, n_slow = _general_line(buf, pos, row, xyz, intensity, rgb, slow, n_slow)
        if status != OK:
            return status, next_line, row, n_slow
        pos = next_line
        row += 1
    return OK, pos, row, n_slow


@nb.njit(cache=True, nogil=True)
def parse_segment(
    buf: np.ndarray,
    readable: int,
    pos: int,
    end: int,
    row: int,
    xyz: np.ndarray,
    intensity: np.ndarray,
    rgb: np.ndarray,
    slow: np.ndarray,
) -> tuple[int, int, int, int]:  # pragma: no cover - compiled
    """Parse the whole lines of ``buf[pos:end]`` into rows from ``row``.

    Returns ``(status, position, row, n_slow)``: on OK the end; on a problem the start
    and row of the offending line. Deferred tokens go to ``slow[:n_slow]`` (start, stop,
    row, column); when ``slow`` is full the segment stops before the current line with
    SLOW_FULL, to be resumed once the caller has converted them.
    """
    return _run(buf, readable, pos, end, row, xyz, intensity, rgb, slow, 0)


@nb.njit(cache=True, nogil=True, parallel=True)
def parse_window(
    buf: np.ndarray,
    readable: int,
    start: int,
    stop: int,
    n_segments: int,
    first_row: int,
    room: int,
    xyz: np.ndarray,
    intensity: np.ndarray,
    rgb: np.ndarray,
    slow: np.ndarray,
    state: np.ndarray,
    n_threads: int,
    drop_start: int = 0,
    drop_stop: int = 0,
) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """Parse the whole lines of ``buf[start:stop]`` in ``n_segments`` segments on
    ``n_threads`` threads, each thread taking the next segment as it comes free
    (:func:`take_next`: equal bytes are not equal time on a loaded machine).

    Segment ``s`` holds the lines that start in the ``s``-th of ``n_segments`` equal byte
    ranges (:func:`line_start`). The thread that counts a segment's lines finds its
    bounds, so no thread touches the window's pages before the counting does (each
    bound is one page first touched, on many cores a few hundred a window). Counts the
    lines of every segment (in parallel); when they are more than ``room``
    rows, the window is cut after the ``room``-th line (only the segment holding the cut
    is scanned for it). Then parses every segment (in parallel) into the rows from
    ``first_row`` on, segment ``s`` at its count's offset; its :func:`parse_segment`
    result and end go to ``state[s]``, its deferred tokens to ``slow[s]``. The pages of
    ``buf[drop_start:drop_stop]`` (page-aligned, of a mapping, parsed before) are dropped
    from the mapping by the thread that takes the first turn, while the others parse. Returns
    ``(lines, segments, end of the window)``. One call per window: the caller runs no
    Python per segment.
    """
    n = max(1, n_segments)
    bounds = np.empty(n + 1, np.int64)
    bounds[n] = stop
    counts = np.empty(n, np.int64)
    taken = np.zeros(2, np.int64)  # segments handed out: counted, then parsed
    for _ in nb.prange(max(1, min(n_threads, n))):
        while True:
            s = take_next(taken[0:1])
            if s >= n:
                break
            low = line_start(buf, start, stop, start + ((stop - start) * s) // n)
            high = line_start(buf, start, stop, start + ((stop - start) * (s + 1)) // n)
            bounds[s] = low
            counts[s] = count_lines(buf, low, high)
    total = 0
    for s in range(n):
        total += counts[s]
    if total > room:  # the batch's last lines: cut inside the segment that reaches room
        before = 0
        cut = 0
        while before + counts[cut] < room:
            before += counts[cut]
            cut += 1
        bounds[cut + 1] = after_newline(buf, bounds[cut], room - before)
        counts[cut] = room - before
        n = cut + 1
        total = room
    rows = np.empty(n, np.int64)
    row = first_row
    for s in range(n):
        rows[s] = row
        row += counts[s]
    for _ in nb.prange(max(1, min(n_threads, n))):
        while True:
            ticket = take_next(taken[1:2])  # 0: the pages to drop, then the segments
            if ticket == 0:
                if drop_stop > drop_start:
                    advise(buf.ctypes.data + drop_start, drop_stop - drop_start, DROP_ADVICE)
                continue
            s = ticket - 1
            if s >= n:
                break
            status, pos, last, n_slow = _run(
                buf, readable, bounds[s], bounds[s + 1], rows[s], xyz, intensity, rgb, slow[s], 0
            )
            state[s, STATE_STATUS] = status
            state[s, STATE_POS] = pos
            state[s, STATE_ROW] = last
            state[s, STATE_SLOW] = n_slow
            state[s, STATE_END] = bounds[s + 1]
    return total, n, bounds[n]


@nb.njit(cache=True, nogil=True)
def line_start(buf: np.ndarray, start: int, stop: int, pos: int) -> int:  # pragma: no cover
    """The first line start of ``buf[start:stop]`` at or after ``pos`` (``stop`` if none):
    segments cut there hold whole lines, and cuts at growing ``pos`` never cross."""
    while start < pos < stop and buf[pos - 1] != 10:
        pos += 1
    return pos


@nb.njit(cache=True, nogil=True)
def count_lines(buf: np.ndarray, start: int, stop: int) -> int:  # pragma: no cover
    """Newlines in ``buf[start:stop]`` (a loop LLVM vectorises).

    The loop runs over a slice from index 0: with ``buf[i]`` for ``i`` from ``start``,
    numba cannot tell the index is never negative and wraps it as a negative index would
    be, a check per byte that kept the loop scalar (1.3-1.9 GB/s here against 5.3-5.7).
    """
    text = buf[start:stop]
    total = 0
    for i in range(text.size):
        total += text[i] == 10
    return total


@nb.njit(cache=True, nogil=True)
def after_newline(buf: np.ndarray, start: int, n_lines: int) -> int:  # pragma: no cover
    """Offset just past the ``n_lines``-th newline from ``start``."""
    pos = start
    seen = 0
    while seen < n_lines:
        seen += buf[pos] == 10
        pos += 1
    return pos


@nb.njit(cache=True, nogil=True)
def gather_tokens(buf: np.ndarray, slow: np.ndarray, width: int) -> np.ndarray:
    """Deferred tokens as a zero-padded ``(n, width)`` byte table (``numpy`` 'S' layout)."""
    table = np.zeros((slow.shape[0], width), np.uint8)
    for i in range(slow.shape[0]):
        start = slow[i, SLOW_START]
        n = min(slow[i, SLOW_STOP] - start, width)
        for k in range(n):
            table[i, k] = buf[start + k]
    return table


@nb.njit(cache=True, nogil=True)
def _write_fixed(out: np.ndarray, pos: int, value: float, decimals: int, scale: float) -> int:
    scaled = np.rint(value * scale)
    negative = scaled < 0
    units = np.int64(-scaled if negative else scaled)
    if negative:
        out[pos] = 45
        pos += 1
    divisor = np.int64(1)
    for _ in range(decimals):
        divisor *= 10
    whole = units // divisor
    fraction = units - whole * divisor
    pos = _write_int(out, pos, whole)
    if decimals > 0:
        out[pos] = 46
        pos += 1
        for d in range(decimals - 1, -1, -1):
            out[pos + d] = 48 + fraction % 10
            fraction //= 10
        pos += decimals
    return pos


@nb.njit(cache=True, nogil=True)
def _write_int(out: np.ndarray, pos: int, value: np.int64) -> int:
    if value < 0:
        out[pos] = 45
        pos += 1
        value = -value
    n_digits = 1
    probe = value
    while probe >= 10:
        probe //= 10
        n_digits += 1
    for d in range(n_digits - 1, -1, -1):
        out[pos + d] = 48 + value % 10
        value //= 10
    return pos + n_digits


MAX_DECIMALS = 9
# sign, 19 digits, point and up to 9 decimals per coordinate; int32 intensity; 3 bytes.
MAX_LINE_BYTES = 3 * 31 + 12 + 3 * 4 + 1


@nb.njit(cache=True, nogil=True, parallel=True)
def format_points(
    xyz: np.ndarray,
    intensity: np.ndarray,
    rgb: np.ndarray,
    labels: np.ndarray,
    decimals: int,
    limit: float,
    n_segments: int,
    n_threads: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Format rows as text in ``n_segments`` buffers on ``n_threads`` threads (each takes
    the next segment as it comes free), their labels (when ``labels`` is not empty) as
    ``.labels`` lines in as many more; return ``(buffers, used, label_buffers,
    label_used, label_counts, bad)``.

    The caller writes ``buffers[s, :used[s]]`` in order (and the labels' likewise); the
    bytes do not depend on the number of segments or threads, so output is
    deterministic. ``label_counts`` counts the rows of each label value; ``bad`` is the
    first row with a coordinate not finite or not below ``limit`` in magnitude (left
    unformatted), or the number of rows when there is none.
    """
    n = xyz.shape[0]
    per_segment = (n + n_segments - 1) // n_segments
    buffers = np.empty((n_segments, max(per_segment, 1) * MAX_LINE_BYTES), np.uint8)
    used = np.zeros(n_segments, np.int64)
    with_labels = labels.shape[0] > 0
    label_buffers = np.empty((n_segments, max(per_segment, 1) * 4 if with_labels else 0), np.uint8)
    label_used = np.zeros(n_segments, np.int64)
    counts = np.zeros((n_segments, 256), np.int64)
    first_bad = np.full(n_segments, n, np.int64)
    scale = 10.0**decimals
    taken = np.zeros(1, np.int64)
    for _ in nb.prange(max(1, min(n_threads, n_segments))):
        while True:
            s = take_next(taken)
            if s >= n_segments:
                break
            out = buffers[s]
            pos = 0
            for i in range(s * per_segment, min(n, (s + 1) * per_segment)):
                if not (
                    abs(xyz[i, 0]) < limit and abs(xyz[i, 1]) < limit and abs(xyz[i, 2]) < limit
                ):
                    first_bad[s] = min(first_bad[s], i)  # NaN fails every comparison
                    continue
                for column in range(3):
                    pos = _write_fixed(out, pos, xyz[i, column], decimals, scale)
                    out[pos] = 32
                    pos += 1
                pos = _write_int(out, pos, np.int64(intensity[i]))
                for column in range(3):
                    out[pos] = 32
                    pos = _write_int(out, pos + 1, np.int64(rgb[i, column]))
                out[pos] = 10
                pos += 1
            used[s] = pos
            if with_labels:
                text = label_buffers[s]
                pos = 0
                for i in range(s * per_segment, min(n, (s + 1) * per_segment)):
                    counts[s, labels[i]] += 1
                    pos = _write_int(text, pos, np.int64(labels[i]))
                    text[pos] = 10
                    pos += 1
                label_used[s] = pos
    return buffers, used, label_buffers, label_used, counts.sum(axis=0), first_bad.min()


@nb.njit(cache=True, nogil=True)
def window_end(buf: np.ndarray, pos: int, target: int, stop: int, max_line: int) -> int:
    """Offset just past the last newline in ``buf[pos:target]``, else past the next one.

    ``buf[:stop]`` ends with a newline. Returns -1 for a line longer than ``max_line``.
    """
    if target >= stop:
        return stop
    i = target - 1
    while i >= pos:
        if buf[i] == 10:
            return i + 1
        i -= 1
    i = target
    while i < stop and buf[i] != 10:
        if i - pos > max_line:
            return -1
        i += 1
    return i + 1
