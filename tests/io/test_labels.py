from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from semantic3d.core import DataFormatError
from semantic3d.io import count_labels, iter_labels, read_labels, write_labels


def _write(tmp_path: Path, text: bytes, name: str = "scan.labels") -> Path:
    path = tmp_path / name
    path.write_bytes(text)
    return path


def test_single_digit_file(tmp_path: Path) -> None:
    path = _write(tmp_path, b"1\n2\n0\n8\n5\n")
    assert read_labels(path).tolist() == [1, 2, 0, 8, 5]
    assert read_labels(path).dtype == np.uint8
    assert count_labels(path) == 5


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (b"1\r\n2\r\n3\r\n", [1, 2, 3]),  # CRLF
        (b"1\n2\n3", [1, 2, 3]),  # no final newline
        (b"1 \n 2\t\n3  \r\n", [1, 2, 3]),  # blanks around values
        (b"10\n255\n0\n", [10, 255, 0]),  # several digits
        (b"", []),  # empty file
    ],
)
def test_tolerated_shapes(tmp_path: Path, text: bytes, expected: list[int]) -> None:
    assert read_labels(_write(tmp_path, text)).tolist() == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            b"1\n2\nx\n4\n",
            r"scan\.labels: line 3: expected one non-negative integer label, found 'x'",
        ),
        (b"1\n2.5\n", r"line 2: expected one non-negative integer label, found '2\.5'"),
        (b"1\n-3\n", r"line 2: expected one non-negative integer label, found '-3'"),
        (b"1\n\n3\n", r"line 2: expected one integer label, found an empty line"),
        (b"1\n2 3\n", r"line 2: expected one non-negative integer label, found '2 3'"),
        (b"1\n256\n", r"line 2: expected a label value in 0\.\.255, found '256'"),
        (b"7\n99999999999999999999\n", r"line 2: expected a label value in 0\.\.255"),
    ],
)
def test_bad_lines_name_file_and_line(tmp_path: Path, text: bytes, message: str) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(DataFormatError, match=message):
        read_labels(path)
    with pytest.raises(DataFormatError, match=message):
        count_labels(path)


def test_line_numbers_count_across_blocks(tmp_path: Path) -> None:
    lines = [b"3\n"] * 1000 + [b"bad\n"] + [b"1\n"] * 10
    path = _write(tmp_path, b"".join(lines))
    with pytest.raises(DataFormatError, match="line 1001: "):
        list(iter_labels(path, block_bytes=64))


def test_chunks_have_exactly_chunk_size(tmp_path: Path) -> None:
    values = np.arange(1000) % 9
    path = tmp_path / "a.labels"
    write_labels(path, [values])
    sizes = [chunk.size for chunk in iter_labels(path, chunk_size=300, block_bytes=128)]
    assert sizes == [300, 300, 300, 100]


def test_invalid_chunk_size(tmp_path: Path) -> None:
    path = _write(tmp_path, b"1\n")
    with pytest.raises(ValueError, match="chunk_size must be a positive integer, found 0"):
        iter_labels(path, chunk_size=0)


def test_write_rejects_values_outside_uint8(tmp_path: Path) -> None:
    with pytest.raises(DataFormatError, match=r"label #2 is 300: expected 0\.\.255"):
        write_labels(tmp_path / "x.labels", [np.array([1, 2, 300])])
    with pytest.raises(DataFormatError, match="expected integer labels, found dtype float64"):
        write_labels(tmp_path / "x.labels", [np.array([1.5])])


def test_writer_output_is_the_benchmark_format(tmp_path: Path) -> None:
    path = tmp_path / "x.labels"
    assert write_labels(path, [np.array([1, 8], np.uint8), np.array([0, 12, 200])]) == 5
    assert path.read_bytes() == b"1\n8\n0\n12\n200\n"


def test_real_labels_files(shared_data: Path) -> None:
    path = shared_data / "oakland" / "oakland_part2_ac.labels"
    labels = read_labels(path)
    assert labels.size == 100_000
    assert set(np.unique(labels)) <= set(range(9))
    reference = np.loadtxt(path, dtype=np.int64)
    np.testing.assert_array_equal(labels, reference)


@settings(max_examples=60, deadline=None)
@given(
    values=arrays(np.uint8, st.integers(0, 400)),
    chunk_size=st.integers(1, 97),
    block_bytes=st.integers(8, 300),
    crlf=st.booleans(),
)
def test_round_trip_and_streaming_equal_one_shot(
    tmp_path_factory: pytest.TempPathFactory,
    values: np.ndarray,
    chunk_size: int,
    block_bytes: int,
    crlf: bool,
) -> None:
    path = tmp_path_factory.mktemp("labels") / "r.labels"
    write_labels(path, [values[: values.size // 2], values[values.size // 2 :]])
    if crlf:
        path.write_bytes(path.read_bytes().replace(b"\n", b"\r\n"))
    whole = read_labels(path)
    np.testing.assert_array_equal(whole, values)
    chunks = list(iter_labels(path, chunk_size=chunk_size, block_bytes=block_bytes))
    assert all(chunk.size == chunk_size for chunk in chunks[:-1])
    joined = np.concatenate(chunks) if chunks else np.empty(0, np.uint8)
    np.testing.assert_array_equal(joined, values)
