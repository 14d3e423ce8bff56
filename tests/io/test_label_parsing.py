"""The numpy label parser (small texts) against the compiled kernels, on the same inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.errors import DataFormatError
from semantic3d.io import _label_grammar as grammar
from semantic3d.io import _label_kernels as kernels
from semantic3d.io import _label_parsing as parsing
from semantic3d.io.labels import read_labels
from semantic3d.io.labelstream import LabelStream

_PIECES = ["0", "3", "8", "9", "12", "255", "256", "0007", "12345678901234567", " ", "\t",
           "\r", "\n", "\n", "\n", "\r\n", "x", "-", "1.5", ""]  # fmt: skip
texts = st.lists(st.sampled_from(_PIECES), max_size=40).map(lambda p: "".join(p).encode())


def _run(parse, data: bytes, args: tuple[int, ...], final: bool, seeded: bool):  # type: ignore[no-untyped-def]
    start, filled, capacity, low, high = args
    buf = np.frombuffer(b"#" * start + data + b"#", np.uint8)[:-1]  # bytes outside the range
    out = np.full(capacity, 77, np.uint8)
    state = np.zeros(grammar.STATE_SIZE, np.int64)
    if seeded:  # a stream already past some lines and problems
        state[[parsing.LINES, parsing.N_SYNTAX, parsing.SYNTAX_LINE]] = (5, 1, 2)
    text = np.full(parsing.TEXT_BYTES, 35, np.uint8)
    done = parse(
        buf, start, start + len(data), final, out, filled, capacity, low, high, state, text
    )
    return tuple(int(v) for v in done), out.tolist(), state.tolist(), text.tolist()


@settings(max_examples=100, deadline=None)
@given(
    data=texts,
    start=st.integers(0, 3),
    filled=st.integers(0, 3),
    room=st.integers(0, 30),
    low=st.integers(0, 3),
    high=st.sampled_from([0, 2, 8, 9, 255]),
    final=st.booleans(),
    seeded=st.booleans(),
)
def test_numpy_parse_lines_equals_the_kernel(
    data: bytes,
    start: int,
    filled: int,
    room: int,
    low: int,
    high: int,
    final: bool,
    seeded: bool,
) -> None:
    args = (start, filled, filled + room, low, high)
    assert _run(parsing._parse_lines_numpy, data, args, final, seeded) == _run(
        kernels.parse_lines, data, args, final, seeded
    )


_PAIRS = ["1\n", "8\n", "0\n", "9\n", "x\n", "12", "1\r", "/\n", ":\n", "0\x0b", "0\t"]


@settings(max_examples=80, deadline=None)
@given(
    data=st.lists(
        st.sampled_from(_PAIRS).map(str.encode) | st.binary(min_size=2, max_size=2), max_size=30
    ),
    offset=st.integers(0, 1),
)
def test_numpy_single_digit_check_equals_the_kernel(data: list[bytes], offset: int) -> None:
    """The kernel reads a line as one 16-bit word: the same count of malformed pairs and
    the same values as the byte pairs, for any bytes (digits' neighbours ``/`` and ``:``,
    line ends' neighbours), from an odd address too."""
    raw = np.frombuffer(b"#" * offset + b"".join(data), np.uint8)[offset:]
    fast, compiled = np.empty(raw.size // 2, np.uint8), np.full(raw.size // 2, 77, np.uint8)
    expected = parsing.parse_single_digit(raw, fast)
    assert expected == sum(not (48 <= pair[0] <= 57 and pair[1] == 10) for pair in data)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(parsing, "SMALL_TEXT_BYTES", -1)  # to the kernel
        assert parsing.parse_single_digit(raw, compiled) == expected
    assert fast.tolist() == compiled.tolist()


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    start=st.integers(0, 3),
    low=st.integers(0, 3),
    high=st.sampled_from([5, 8, 9, 255]),
    odd=st.lists(
        st.tuples(st.integers(0, 3 * kernels._WINDOW), st.sampled_from(["x", "12", "\r", ""])),
        max_size=3,
    ),
    final=st.booleans(),
)
def test_windows_of_single_digit_lines_parse_as_numpy_does(
    seed: int, start: int, low: int, high: int, odd: list[tuple[int, str]], final: bool
) -> None:
    """Texts long enough for the kernel's windows of ``d\\n`` lines (read as 16-bit words,
    from odd offsets too), with digits out of ``low..high`` and lines of other shapes
    inside windows: the same values, problems and positions as the numpy parser."""
    lines = [str(d) for d in np.random.default_rng(seed).integers(0, 10, 3 * kernels._WINDOW + 7)]
    for at, text in odd:
        lines[at] = text
    data = ("\n".join(lines) + "\n").encode()
    room = len(lines) + 2
    args = (start, 0, room, low, high)
    assert _run(parsing._parse_lines_numpy, data, args, final, False) == _run(
        kernels.parse_lines, data, args, final, False
    )


def _outcome(path: Path) -> object:
    try:
        return read_labels(path).tolist()
    except DataFormatError as exc:
        return str(exc)


@settings(max_examples=30, deadline=None)
@given(data=texts)
def test_read_labels_gives_the_same_values_and_errors_either_way(
    data: bytes, tmp_path_factory: pytest.TempPathFactory
) -> None:
    path = tmp_path_factory.getbasetemp() / "scan.labels"
    path.write_bytes(data)
    small = _outcome(path)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(parsing, "SMALL_TEXT_BYTES", -1)  # every text to the kernels
        assert _outcome(path) == small


def test_a_small_text_is_parsed_without_the_kernels_and_a_long_one_with_them() -> None:
    assert parsing._use_numpy(parsing.SMALL_TEXT_BYTES)
    assert not parsing._use_numpy(parsing.SMALL_TEXT_BYTES + 1)


def test_many_irregular_lines_go_to_the_kernel() -> None:
    data = b"10\n" * (parsing._SMALL_IRREGULAR_LINES + 1)
    buf = np.frombuffer(data, np.uint8)
    state = np.zeros(grammar.STATE_SIZE, np.int64)
    text = np.zeros(parsing.TEXT_BYTES, np.uint8)
    out = np.empty(len(data) // 3, np.uint8)
    args = (buf, 0, buf.size, True, out, 0, out.size, 0, 255, state, text)
    assert parsing._parse_lines_numpy(*args) is None
    assert parsing.parse_lines(*args) == (buf.size, out.size)
    assert set(out.tolist()) == {10}


def test_label_stream_problems_are_the_same_either_way() -> None:
    import io

    data = b"1\n\n9\r\n 300 \nx\n2"
    messages = []
    for threshold in (parsing.SMALL_TEXT_BYTES, -1):
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(parsing, "SMALL_TEXT_BYTES", threshold)
            stream = LabelStream(io.BytesIO(data), source="p.labels", low=1, high=8)
            assert stream.read(10).tolist() == [1, 0, 0, 0, 0, 2]
            messages.append(stream.problems())
    assert messages[0] == messages[1]
    assert messages[0][0] == (
        "p.labels: line 2: expected an integer label value 1..8, found an empty line "
        "(1 more line is not an integer)"
    )
