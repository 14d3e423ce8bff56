"""``LabelStream``: a checking parser of ``.labels`` byte streams (files or zip members).

Where :func:`semantic3d.io.labels.iter_labels` reads a path and stops at the first bad
line, ``LabelStream`` reads any binary stream (benchmark submissions arrive as zip members
that must be streamed, never extracted) and collects *every* problem of a file (how many
bad lines, the first one of each kind) in one pass, as submission validation must. Both
run the same parser (:func:`semantic3d.io._label_parsing.parse_lines`: numpy for small
texts, compiled kernels for long ones). The evaluator parses every line of another shape
with it; runs of one-digit lines it may check and count itself, from :meth:`buffered`
bytes it then skips with :meth:`skip_checked_lines`.

Format accepted: one integer a line, ``\\n`` or ``\\r\\n`` line ends, spaces or tabs
around the value tolerated, the last line with or without a line end. An empty line, a
sign, a decimal point or any other character is a syntax problem.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from semantic3d.io import _label_parsing as parsing
from semantic3d.io._label_grammar import (
    LINES,
    N_RANGE,
    N_SYNTAX,
    RANGE_LINE,
    RANGE_VALUE,
    STATE_SIZE,
    SYNTAX_LINE,
    TEXT_BYTES,
    TEXT_LEN,
    VALUE_CAP,
)


class ReadableStream(Protocol):
    """What :class:`LabelStream` reads from: a binary stream with ``readinto``."""

    def readinto(self, buffer: Any, /) -> int | None:
        """Fill ``buffer``; return the bytes read (0 at the end)."""
        ...


DEFAULT_BLOCK_SIZE = 4 << 20
"""Bytes read from the stream at a time."""


class LabelStream:
    """Parse label values from a binary stream, checking every line.

    Values outside ``low..high`` and lines that are not integers are counted (the first
    of each is remembered for the message) and come out as 0; parsing goes on, so one
    pass reports every problem. The stream is read in blocks of ``block_size`` bytes:
    memory stays constant whatever the file size.

    Args:
        stream: a binary file object (a file opened ``"rb"``, a ``zipfile`` member).
        source: the name used in problem messages.
        low, high: the accepted range of label values.
    """

    def __init__(
        self,
        stream: ReadableStream,
        *,
        source: str,
        low: int,
        high: int,
        block_size: int = DEFAULT_BLOCK_SIZE,
    ) -> None:
        if block_size < 16:
            raise ValueError(f"block_size: expected at least 16 bytes, found {block_size}")
        self.source = source
        self._stream = stream
        self._low = low
        self._high = high
        self._buf = np.empty(block_size, dtype=np.uint8)
        self._view = memoryview(self._buf)  # type: ignore[arg-type]
        self._pos = 0
        self._end = 0
        self._eof = False
        self._skipping = False  # inside an over-long line, discarding to its end
        self._state = np.zeros(STATE_SIZE, dtype=np.int64)
        self._text = np.zeros(TEXT_BYTES, dtype=np.uint8)
        self.bytes_read = 0

    @property
    def n_lines(self) -> int:
        """Lines parsed so far (after :meth:`drain`, the lines of the whole stream)."""
        return int(self._state[LINES])

    @property
    def has_problems(self) -> bool:
        """True once a line was not an integer or out of range."""
        return bool(self._state[N_SYNTAX] or self._state[N_RANGE])

    @property
    def exhausted(self) -> bool:
        """True once every byte of the stream has been parsed."""
        return self._eof and self._pos >= self._end and not self._skipping

    def _refill(self) -> bool:
        """Move the partial line to the front and read more; True if it fills the buffer."""
        carry = self._end - self._pos
        if carry:
            self._buf[:carry] = self._buf[self._pos : self._end]
        self._pos, self._end = 0, carry
        if carry == self._buf.shape[0]:
            self._start_overlong_line()
            return True
        got = self._stream.readinto(self._view[carry:])
        got = got or 0
        self.bytes_read += got
        self._end += got
        self._eof = got == 0
        return False

    def _start_overlong_line(self) -> None:
        """A line longer than the whole buffer: count it as one syntax problem, skip it."""
        state = self._state
        state[LINES] += 1
        if state[N_SYNTAX] == 0:
            state[SYNTAX_LINE] = state[LINES]
            self._text[:] = self._buf[:TEXT_BYTES]
            state[TEXT_LEN] = TEXT_BYTES
        state[N_SYNTAX] += 1
        self._pos = self._end = 0
        self._skipping = True

    def _skip_overlong_line(self) -> None:
        while self._skipping:
            if self._pos >= self._end:
                got = self._stream.readinto(self._view) or 0
                self.bytes_read += got
                self._pos, self._end = 0, got
                if got == 0:
                    self._eof = True
                    self._skipping = False
                    return
            newlines = np.flatnonzero(self._buf[self._pos : self._end] == 10)
            if newlines.size:
                self._pos += int(newlines[0]) + 1
                self._skipping = False
            else:
                self._pos = self._end

    def read(self, n_values: int) -> NDArray[np.uint8]:
        """The next ``n_values`` values (fewer only when the stream ends)."""
        out = np.empty(n_values, dtype=np.uint8)
        filled = 0
        while filled < n_values:
            if self._skipping:
                self._skip_overlong_line()
            self._pos, filled = parsing.parse_lines(
                self._buf,
                self._pos,
                self._end,
                self._eof,
                out,
                filled,
                n_values,
                self._low,
                self._high,
                self._state,
                self._text,
            )
            if filled == n_values or (self._eof and self._pos >= self._end):
                break
            if self._refill():  # an over-long line: one bad value, like any bad line
                out[filled] = 0
                filled += 1
        return out[:filled]

    def buffered(self, min_bytes: int) -> tuple[NDArray[np.uint8], int, int]:
        """The bytes read and not yet parsed, as ``(buffer, start, end)``.

        Reads more first when fewer than ``min_bytes`` are buffered and the stream has
        more (``min_bytes`` at most half the block size). ``start`` is a line start. For a
        caller that parses whole lines itself and then calls :meth:`skip_checked_lines`;
        the buffer's bytes are valid until the next call of any other method.
        """
        if not 0 < min_bytes <= self._buf.shape[0] // 2:
            raise ValueError(f"min_bytes: expected 1..{self._buf.shape[0] // 2}, found {min_bytes}")
        if not self._skipping and not self._eof and self._end - self._pos < min_bytes:
            self._refill()
        if self._skipping:
            return self._buf, self._pos, self._pos
        return self._buf, self._pos, self._end

    def skip_checked_lines(self, n_lines: int, n_bytes: int) -> None:
        """Move past ``n_lines`` whole lines (``n_bytes``) from the start of :meth:`buffered`.

        The caller parsed them and found each an integer within this stream's range: they
        are counted as lines, with no problem.
        """
        if not 0 <= n_bytes <= self._end - self._pos or n_lines < 0:
            raise ValueError(
                f"skip_checked_lines: expected at most {self._end - self._pos} buffered "
                f"bytes, found {n_bytes} bytes of {n_lines} lines"
            )
        self._pos += n_bytes
        self._state[LINES] += n_lines

    @property
    def value_range(self) -> tuple[int, int]:
        """The accepted label values, ``(low, high)``."""
        return self._low, self._high

    def drain(self, *, chunk_size: int = 1 << 20) -> int:
        """Parse the rest of the stream (counting lines and problems); values left over."""
        left = 0
        while not self.exhausted:
            got = self.read(chunk_size).shape[0]
            left += got
            if got < chunk_size:
                break
        return left

    def problems(self) -> list[str]:
        """Messages for the problems seen so far (first bad line of each kind + count)."""
        state = self._state
        found: list[str] = []
        expected = f"expected an integer label value {self._low}..{self._high}"
        if state[N_SYNTAX]:
            raw = bytes(self._text[: state[TEXT_LEN]]).rstrip(b"\r\n")
            shown = raw.decode("utf-8", "replace")
            what = f"{shown!r}" if shown.strip() else "an empty line"
            found.append(
                f"{self.source}: line {state[SYNTAX_LINE]}: {expected}, found {what}"
                + _more(int(state[N_SYNTAX]), "line is not an integer", "lines are not integers")
            )
        if state[N_RANGE]:
            value = int(state[RANGE_VALUE])
            shown_value = str(value) if value < VALUE_CAP else "a number of 16 digits or more"
            found.append(
                f"{self.source}: line {state[RANGE_LINE]}: {expected}, found {shown_value}"
                + _more(int(state[N_RANGE]), "line is out of range", "lines are out of range")
            )
        return found


def _more(count: int, singular: str, plural: str) -> str:
    """`` (N more lines ...)`` when a problem repeats."""
    extra = count - 1
    if extra <= 0:
        return ""
    return f" ({extra} more {singular if extra == 1 else plural})"
