"""LabelStream: the checking .labels parser, against numpy and the io reader."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.io.labels import read_labels
from semantic3d.io.labelstream import LabelStream


def _stream(data: bytes, *, low: int = 0, high: int = 255, block_size: int = 64) -> LabelStream:
    return LabelStream(
        io.BytesIO(data), source="x.labels", low=low, high=high, block_size=block_size
    )


def _read_all(stream: LabelStream, chunk: int) -> np.ndarray:
    parts = []
    while True:
        part = stream.read(chunk)
        parts.append(part)
        if part.size < chunk:
            return np.concatenate(parts)


@settings(max_examples=80, deadline=None)
@given(
    values=st.lists(st.integers(0, 255), max_size=300),
    crlf=st.booleans(),
    final_newline=st.booleans(),
    padded=st.booleans(),
    block_size=st.integers(16, 80),
    chunk=st.integers(1, 50),
)
def test_streaming_parse_equals_the_values_written(
    values: list[int], crlf: bool, final_newline: bool, padded: bool, block_size: int, chunk: int
) -> None:
    end = "\r\n" if crlf else "\n"
    pad = " \t" if padded else ""
    text = end.join(f"{pad}{v}{pad}" for v in values)
    if values and final_newline:
        text += end
    stream = _stream(text.encode(), block_size=block_size)
    np.testing.assert_array_equal(_read_all(stream, chunk), np.array(values, dtype=np.uint8))
    assert stream.n_lines == len(values)
    assert stream.problems() == []
    assert stream.exhausted


def test_agrees_with_the_io_reader_on_a_real_file(shared_data: Path) -> None:
    path = shared_data / "oakland" / "oakland_part2_ah.labels"
    with path.open("rb", buffering=0) as handle:
        stream = LabelStream(handle, source=path.name, low=0, high=8)
        values = _read_all(stream, 1 << 16)
    np.testing.assert_array_equal(values, read_labels(path))
    assert stream.bytes_read == path.stat().st_size


def test_counts_every_bad_line_and_remembers_the_first() -> None:
    stream = _stream(b"1\nabc\n2\n\n3.5\n-1\n9\n12\n0\n", low=1, high=8)
    values = stream.read(100)
    assert values.tolist() == [1, 0, 2, 0, 0, 0, 0, 0, 0]
    assert stream.n_lines == 9
    assert stream.problems() == [
        "x.labels: line 2: expected an integer label value 1..8, found 'abc' "
        "(3 more lines are not integers)",
        "x.labels: line 7: expected an integer label value 1..8, found 9 "
        "(2 more lines are out of range)",
    ]


def test_empty_line_is_named() -> None:
    stream = _stream(b"1\n\n2\n", low=0, high=8)
    stream.drain()
    assert stream.problems() == [
        "x.labels: line 2: expected an integer label value 0..8, found an empty line"
    ]


def test_line_longer_than_the_buffer_is_one_problem() -> None:
    stream = _stream(b"1\n" + b"7" * 500 + b"\n2\n", low=0, high=8, block_size=32)
    values = _read_all(stream, 10)
    assert stream.n_lines == 3
    np.testing.assert_array_equal(values, [1, 0, 2])  # one value per line, bad ones 0
    (problem,) = stream.problems()
    assert problem.startswith("x.labels: line 2: expected an integer label value 0..8, found '777")


def test_huge_numbers_do_not_overflow() -> None:
    stream = _stream(b"99999999999999999999999999\n5\n", low=0, high=8)
    np.testing.assert_array_equal(stream.read(10), [0, 5])
    assert stream.problems() == [
        "x.labels: line 1: expected an integer label value 0..8, "
        "found a number of 16 digits or more"
    ]


def test_block_size_must_hold_a_line() -> None:
    with pytest.raises(ValueError, match="block_size: expected at least 16 bytes"):
        LabelStream(io.BytesIO(b""), source="x", low=0, high=8, block_size=4)


@settings(max_examples=40, deadline=None)
@given(
    n_lines=st.integers(0, 20_000),
    bad=st.lists(
        st.tuples(st.integers(0, 19_999), st.sampled_from(["0", "9", "x", "12", "3\r"])), max_size=4
    ),
    block_size=st.sampled_from([64, 9_000, 40_000, 1 << 20]),
    chunk=st.sampled_from([1_000, 4_096, 50_000]),
)
def test_long_single_digit_files_with_rare_problems(
    n_lines: int, bad: list[tuple[int, str]], block_size: int, chunk: int
) -> None:
    """Exercises the windowed fast path (4096 lines at once) and its fallback."""
    rng = np.random.default_rng(n_lines)
    lines = [str(v) for v in rng.integers(1, 9, n_lines)]
    for position, text in bad:
        if position < n_lines:
            lines[position] = text
    stream = _stream(
        ("\n".join(lines) + "\n").encode() if lines else b"", low=1, high=8, block_size=block_size
    )
    values = _read_all(stream, chunk)
    expected = [int(t) if t.strip().isdigit() and 1 <= int(t) <= 8 else 0 for t in lines]
    np.testing.assert_array_equal(values, np.array(expected, dtype=np.uint8))
    assert stream.n_lines == n_lines
    syntax = [k for k, t in enumerate(lines) if not t.strip().isdigit()]
    out_of_range = [k for k, t in enumerate(lines) if t.strip().isdigit() and not 1 <= int(t) <= 8]
    problems = stream.problems()
    assert len(problems) == bool(syntax) + bool(out_of_range)
    if syntax:
        assert problems[0].startswith(f"x.labels: line {syntax[0] + 1}: ")
    if out_of_range:
        assert problems[-1].startswith(f"x.labels: line {out_of_range[0] + 1}: ")


@pytest.mark.parametrize("high", [8, 9, 12, 255])
def test_long_files_reject_non_digits_whatever_the_range(high: int) -> None:
    """The windowed fast path checks digits, not just the range (``'x' - '0'`` is 72)."""
    data = b"1\n" * 5_000 + b"x\n" + b"1\n" * 5_000
    stream = _stream(data, low=0, high=high, block_size=1 << 16)
    values = _read_all(stream, 1 << 14)
    assert values.size == 10_001 and values[5_000] == 0
    assert stream.problems() == [
        f"x.labels: line 5001: expected an integer label value 0..{high}, found 'x'"
    ]


@settings(max_examples=60, deadline=None)
@given(
    values=st.lists(st.integers(0, 9), min_size=1, max_size=200),
    block_size=st.integers(16, 80),
    skips=st.lists(st.integers(0, 20), max_size=10),
)
def test_lines_checked_by_the_caller_are_skipped_and_counted(
    values: list[int], block_size: int, skips: list[int]
) -> None:
    """A caller parsing ``d\\n`` lines from ``buffered`` and skipping them leaves the stream
    where reading them would have: the values after them, the same line count."""
    data = "".join(f"{v}\n" for v in values).encode()
    stream = _stream(data, block_size=block_size)
    taken: list[int] = []
    for want in skips:
        buf, start, end = stream.buffered(block_size // 2)
        n_lines = min(want, (end - start) // 2)
        taken.extend(int(b) - 48 for b in buf[start : start + 2 * n_lines : 2])
        stream.skip_checked_lines(n_lines, 2 * n_lines)
        assert stream.n_lines == len(taken)
    rest = _read_all(stream, 7)
    assert taken + rest.tolist() == values
    assert stream.n_lines == len(values)
    assert stream.problems() == []


def test_buffered_and_skip_refuse_what_they_cannot_do() -> None:
    stream = _stream(b"1\n2\n", block_size=32)
    with pytest.raises(ValueError, match=r"min_bytes: expected 1\.\.16, found 17"):
        stream.buffered(17)
    buf, start, end = stream.buffered(16)
    assert bytes(buf[start:end]) == b"1\n2\n"
    with pytest.raises(ValueError, match="at most 4 buffered bytes, found 6 bytes"):
        stream.skip_checked_lines(3, 6)
    assert stream.value_range == (0, 255)
    assert stream.read(5).tolist() == [1, 2]
