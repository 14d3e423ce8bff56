"""The shared constants of both ``.labels`` parsers (numpy and compiled).

A module of its own so that the numpy parser, which imports the compiled kernels on first
use, and the kernels, which need the same slots, import no cycle.
"""

from __future__ import annotations

# Slots of the int64 ``state`` array of parse_lines: lines parsed; syntax problems, the
# line of the first; out-of-range values, the line and value of the first; bytes of the
# first bad line's text kept in ``text``.
LINES, N_SYNTAX, SYNTAX_LINE, N_RANGE, RANGE_LINE, RANGE_VALUE, TEXT_LEN = range(7)
STATE_SIZE = 7
TEXT_BYTES = 24
"""Bytes of the first bad line kept for messages."""
VALUE_CAP = 10**15
"""Digits past this are not accumulated (no int64 overflow); larger values stay >= it."""
