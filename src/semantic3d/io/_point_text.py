"""Semantic3D point text without numba: the problem codes, their messages, and a parser
for small files.

Importing numba and loading the cached kernels of :mod:`semantic3d.io._ascii_kernels`
costs about a CPU-second, while parsing a scan of a few thousand lines in Python takes a
few hundredths. Regular files up to :data:`SMALL_FILE_BYTES` are therefore parsed here,
token by token with the kernels' grammar, and everything else by the kernels. Both give
the same arrays and the same :class:`~semantic3d.core.errors.DataFormatError` (same line,
same message) for the same file: ``tests/io/test_point_text.py`` checks it with
hypothesis.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from semantic3d.core.errors import DataFormatError
from semantic3d.core.pointcloud import PointCloud

COLUMNS = ("x", "y", "z", "intensity", "r", "g", "b")
N_COLUMNS = 7
MAX_LINE_BYTES = 1 << 20
"""A longer line means the file is binary or not line based."""

# Problem codes shared with the compiled kernels (one definition for both parsers).
OK = 0
BAD_NUMBER = 1  # a token that is not a decimal number
COLUMN_COUNT = 2  # fewer or more than 7 columns
NOT_INTEGER = 3  # intensity/r/g/b with a fraction
OUT_OF_RANGE = 4  # rgb outside 0..255, intensity outside int32
NON_FINITE = 5  # a number beyond float64 (``1e400``)
SLOW_FULL = 6  # internal to the kernels: the deferred-token list of a segment is full

SMALL_FILE_BYTES = 256 << 10
"""Regular files up to this size are parsed here; larger ones by the compiled kernels."""

_EXACT_DIGITS = 15  # the kernels defer tokens past these (to the general conversion) ...
_EXACT_EXPONENT = 22  # ... or with a decimal exponent beyond this
_EXPONENT_CAP = 100_000  # the kernels stop accumulating exponent digits past this
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\Z", re.ASCII)
_TOKEN = re.compile(rb"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_BLANKS = re.compile(rb"[ \t]*")
_LINE_END = re.compile(rb"[ \t\r]*\Z")
_DELIMITERS = frozenset(b" \t\r")
_INTEGER_RANGES = ((-2147483648.0, 2147483647.0), (0.0, 255.0), (0.0, 255.0), (0.0, 255.0))


def iter_small_points(path: Path, data: bytes, chunk_size: int) -> Iterator[PointCloud]:
    """Chunks of exactly ``chunk_size`` points of the text ``data`` read from ``path``.

    Raises the :class:`DataFormatError` the kernels raise, before yielding anything (as
    they do for a file this small: its lines fit one batch).
    """
    lines = data.split(b"\n")
    if lines[-1] == b"":
        lines.pop()  # the text ends with a line end (or is empty)
    n = len(lines)
    xyz = np.empty((n, 3), np.float64)
    intensity = np.empty(n, np.int32)
    rgb = np.empty((n, 3), np.uint8)
    for row, line in enumerate(lines):
        status, values = _parse_line(line)
        if status != OK:
            start = sum(len(earlier) + 1 for earlier in lines[:row])
            text = line_at(np.frombuffer(data, np.uint8), start)
            raise point_error(path, text, status, row + 1)
        xyz[row] = values[:3]
        intensity[row] = values[3]
        rgb[row] = values[4:]
    for start in range(0, n, chunk_size):
        stop = min(start + chunk_size, n)
        yield PointCloud(xyz[start:stop], intensity[start:stop], rgb[start:stop])


def _parse_line(line: bytes) -> tuple[int, list[float]]:
    """``(status, values)`` of one line (its text without the line end).

    The kernels' grammar: seven tokens separated by spaces or tabs, each
    ``[+-]digits[.digits][e[+-]digits]`` followed by a blank, a carriage return or the
    line end; then only blanks or carriage returns. Problems are reported as the kernels
    do: the first token that is malformed or (when the kernels convert it at once) an
    invalid intensity or colour; then, on an otherwise valid line, the first of the
    tokens they defer to the general conversion that is invalid.
    """
    values: list[float] = []
    deferred: list[int] = []
    pos = 0
    size = len(line)
    for column in range(N_COLUMNS):
        pos = _BLANKS.match(line, pos).end()  # type: ignore[union-attr]
        if pos == size or line[pos] == 13:
            return COLUMN_COUNT, values
        match = _TOKEN.match(line, pos)
        if match is None:
            return BAD_NUMBER, values
        stop = match.end()
        if stop < size and line[stop] not in _DELIMITERS:
            return BAD_NUMBER, values
        token = match.group()
        value = float(token)
        values.append(value)
        if _deferred(token):
            deferred.append(column)
        elif column >= 3:
            status = _integer_status(column, value)
            if status != OK:
                return status, values
        pos = stop
    if _LINE_END.match(line, pos) is None:
        return COLUMN_COUNT, values
    for column in deferred:
        value = values[column]
        if not math.isfinite(value):
            return NON_FINITE, values
        if column >= 3:
            status = _integer_status(column, value)
            if status != OK:
                return status, values
    return OK, values


def _integer_status(column: int, value: float) -> int:
    if value != math.floor(value):
        return NOT_INTEGER
    low, high = _INTEGER_RANGES[column - 3]
    return OUT_OF_RANGE if value < low or value > high else OK


def _deferred(token: bytes) -> bool:
    """Whether the kernels leave ``token`` to the general conversion: a non-zero value of
    more than 15 significant digits, or whose decimal exponent is beyond ±22."""
    mantissa, _, exponent_text = token.lstrip(b"+-").lower().partition(b"e")
    whole, _, fraction = mantissa.partition(b".")
    significant = (whole + fraction).lstrip(b"0")
    if not significant:
        return False  # zero: exact whatever the exponent
    if len(significant) > _EXACT_DIGITS:
        return True
    written = 0
    for digit in exponent_text.lstrip(b"+-"):
        if written >= _EXPONENT_CAP:
            break
        written = written * 10 + digit - 48
    exponent = -written if exponent_text.startswith(b"-") else written
    return not -_EXACT_EXPONENT <= exponent - len(fraction) <= _EXACT_EXPONENT


def line_at(buf: np.ndarray, pos: int, limit: int = 200) -> str:
    """The text of the line holding ``pos`` (at most ``limit`` bytes), for messages."""
    start = pos
    while start > 0 and buf[start - 1] != 10 and pos - start < MAX_LINE_BYTES:
        start -= 1
    stop = start
    while stop < buf.size and buf[stop] != 10 and stop - start < limit:
        stop += 1
    return bytes(buf[start:stop]).decode("utf-8", errors="replace").rstrip("\r")


def long_line_error(path: Path) -> DataFormatError:
    """A line longer than :data:`MAX_LINE_BYTES`."""
    return DataFormatError(
        f"expected text lines, found a line longer than {MAX_LINE_BYTES} bytes (binary data?)",
        path=str(path),
    )


def point_error(path: Path, text: str, status: int, line: int) -> DataFormatError:
    """The error for problem ``status`` on ``line`` of ``path``, whose text is ``text``."""
    tokens = text.split()
    if status == COLUMN_COUNT:
        detail = f"expected {len(COLUMNS)} columns ({' '.join(COLUMNS)}), found {len(tokens)}"
    elif status == BAD_NUMBER:
        bad = next((t for t in tokens if not _NUMBER.match(t)), text)
        detail = f"expected numbers in every column, found {bad!r}"
    elif status == NON_FINITE:
        bad = next((t for t in tokens if not np.isfinite(float(t))), text)
        detail = f"expected finite numbers (within float64) in every column, found {bad!r}"
    elif status == NOT_INTEGER:
        bad = next((t for t in tokens[3:] if float(t) % 1), "")
        detail = f"expected integer intensity and colour values, found {bad!r}"
    else:
        detail = f"expected r g b in 0..255 and an int32 intensity, found {' '.join(tokens[3:7])!r}"
    return DataFormatError(detail, path=str(path), line=line)
