"""Compiled kernels for Semantic3D point text: ``x y z intensity r g b`` per line.

Hand-written because this is the hottest IO path (scans of ~500 M lines, 17 GB): a
specialised number scanner run on both cores beats pyarrow's and pandas' general CSV
readers by a wide margin on this machine (see ``benchmarks/bench_io.py``). The block is
split into whole-line segments; pass one counts lines per segment, pass two parses each
segment into its slice of the output in parallel.

Numbers are scanned as a decimal mantissa and a power of ten. With at most 15
significant digits and an exponent within ±22, ``mantissa / 10**k`` is correctly rounded
(both operands are exact doubles), so results equal Python's ``float()``; longer
mantissas are truncated to 18 digits, within an ulp of the exact value.
"""

from __future__ import annotations

import numba as nb
import numpy as np

N_COLUMNS = 7
OK = 0
BAD_NUMBER = 1  # a token that is not a finite decimal number
COLUMN_COUNT = 2  # fewer or more than 7 columns
NOT_INTEGER = 3  # intensity/r/g/b with a fraction
OUT_OF_RANGE = 4  # rgb outside 0..255, intensity outside int32

_POW10 = np.array([10.0**i for i in range(23)], dtype=np.float64)


@nb.njit(cache=True, nogil=True, inline="always")
def _is_blank(c: int) -> bool:
    return c == 32 or c == 9 or c == 13


@nb.njit(cache=True, nogil=True)
def _parse_number(block: np.ndarray, pos: int, pow10: np.ndarray) -> tuple[float, int, bool]:
    """Scan one number at ``pos``; return ``(value, next_pos, ok)``."""
    c = block[pos]
    negative = False
    if c == 45 or c == 43:
        negative = c == 45
        pos += 1
        c = block[pos]
    mantissa = 0
    n_significant = 0
    exponent = 0
    n_digits = 0
    while c >= 48 and c <= 57:
        if n_significant < 18:
            mantissa = mantissa * 10 + (c - 48)
            if mantissa:
                n_significant += 1
        else:
            exponent += 1
        n_digits += 1
        pos += 1
        c = block[pos]
    if c == 46:
        pos += 1
        c = block[pos]
        while c >= 48 and c <= 57:
            if n_significant < 18:
                mantissa = mantissa * 10 + (c - 48)
                exponent -= 1
                if mantissa:
                    n_significant += 1
            n_digits += 1
            pos += 1
            c = block[pos]
    if n_digits == 0:
        return 0.0, pos, False
    if c == 101 or c == 69:
        pos += 1
        c = block[pos]
        exp_negative = False
        if c == 45 or c == 43:
            exp_negative = c == 45
            pos += 1
            c = block[pos]
        exp_value = 0
        exp_digits = 0
        while c >= 48 and c <= 57:
            if exp_value < 100000:
                exp_value = exp_value * 10 + (c - 48)
            exp_digits += 1
            pos += 1
            c = block[pos]
        if exp_digits == 0:
            return 0.0, pos, False
        exponent += -exp_value if exp_negative else exp_value
    value = float(mantissa)
    if mantissa == 0:
        value = 0.0
    elif exponent < 0:
        value = value / pow10[-exponent] if exponent >= -22 else value * 10.0**exponent
    elif exponent > 0:
        value = value * pow10[exponent] if exponent <= 22 else value * 10.0**exponent
    if negative:
        value = -value
    if not (c == 32 or c == 9 or c == 13 or c == 10):
        return 0.0, pos, False
    return value, pos, True


@nb.njit(cache=True, nogil=True)
def _parse_segment(
    block: np.ndarray,
    start: int,
    end: int,
    first: int,
    xyz: np.ndarray,
    intensity: np.ndarray,
    rgb: np.ndarray,
    pow10: np.ndarray,
) -> tuple[int, int]:
    """Parse the whole lines in ``block[start:end]`` into rows from ``first``.

    Returns ``(status, bad_row)`` for the first problem, ``(OK, -1)`` otherwise.
    """
    row = first
    pos = start
    while pos < end:
        for column in range(N_COLUMNS):
            c = block[pos]
            while c == 32 or c == 9:
                pos += 1
                c = block[pos]
            if c == 10 or c == 13:
                return COLUMN_COUNT, row
            value, pos, ok = _parse_number(block, pos, pow10)
            if not ok:
                return BAD_NUMBER, row
            if column < 3:
                xyz[row, column] = value
            else:
                if value != np.floor(value):
                    return NOT_INTEGER, row
                if column == 3:
                    if value < -2147483648.0 or value > 2147483647.0:
                        return OUT_OF_RANGE, row
                    intensity[row] = np.int32(value)
                else:
                    if value < 0.0 or value > 255.0:
                        return OUT_OF_RANGE, row
                    rgb[row, column - 4] = np.uint8(value)
        c = block[pos]
        while c == 32 or c == 9 or c == 13:
            pos += 1
            c = block[pos]
        if c != 10:
            return COLUMN_COUNT, row
        pos += 1
        row += 1
    return OK, -1


@nb.njit(cache=True, nogil=True)
def _segment_bounds(block: np.ndarray, n_segments: int) -> np.ndarray:
    """Byte offsets splitting ``block`` into ``n_segments`` runs of whole lines."""
    n_bytes = block.shape[0]
    bounds = np.empty(n_segments + 1, np.int64)
    bounds[0] = 0
    for s in range(1, n_segments):
        pos = max((n_bytes * s) // n_segments, bounds[s - 1])
        while pos < n_bytes and block[pos - 1] != 10:
            pos += 1
        bounds[s] = pos
    bounds[n_segments] = n_bytes
    return bounds


@nb.njit(cache=True, nogil=True, parallel=True)
def parse_points(
    block: np.ndarray, n_segments: int, pow10: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """Parse a block of whole lines; return ``(xyz, intensity, rgb, status, bad_row)``."""
    bounds = _segment_bounds(block, n_segments)
    counts = np.zeros(n_segments + 1, np.int64)
    for s in nb.prange(n_segments):
        total = 0
        for i in range(bounds[s], bounds[s + 1]):
            total += block[i] == 10
        counts[s + 1] = total
    offsets = np.cumsum(counts)
    n_rows = offsets[n_segments]
    xyz = np.empty((n_rows, 3), np.float64)
    intensity = np.empty(n_rows, np.int32)
    rgb = np.empty((n_rows, 3), np.uint8)
    statuses = np.zeros(n_segments, np.int64)
    bad_rows = np.full(n_segments, -1, np.int64)
    for s in nb.prange(n_segments):
        status, bad_row = _parse_segment(
            block, bounds[s], bounds[s + 1], offsets[s], xyz, intensity, rgb, pow10
        )
        statuses[s] = status
        bad_rows[s] = bad_row
    for s in range(n_segments):
        if statuses[s] != OK:
            return xyz, intensity, rgb, statuses[s], bad_rows[s]
    return xyz, intensity, rgb, OK, -1


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
    xyz: np.ndarray, intensity: np.ndarray, rgb: np.ndarray, decimals: int, n_segments: int
) -> tuple[np.ndarray, np.ndarray]:
    """Format rows as text in ``n_segments`` parallel buffers; return ``(buffers, used)``.

    The caller writes ``buffers[s, :used[s]]`` in order; the bytes do not depend on the
    number of threads, so output is deterministic.
    """
    n = xyz.shape[0]
    per_segment = (n + n_segments - 1) // n_segments
    buffers = np.empty((n_segments, max(per_segment, 1) * MAX_LINE_BYTES), np.uint8)
    used = np.zeros(n_segments, np.int64)
    scale = 10.0**decimals
    for s in nb.prange(n_segments):
        out = buffers[s]
        pos = 0
        for i in range(s * per_segment, min(n, (s + 1) * per_segment)):
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
    return buffers, used
