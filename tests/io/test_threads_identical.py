"""Reading gives the same arrays on any number of threads (segments, windows and pieces
split differently), and large ``.labels`` read by the fast path equal the checking parser's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from semantic3d.core.errors import DataFormatError
from semantic3d.core.threads import thread_limit
from semantic3d.io import iter_ascii_points, iter_labels, read_labels
from semantic3d.io.ascii import write_ascii_points
from semantic3d.io.chunks import concatenate_arrays
from semantic3d.io.labels import _iter_label_blocks
from tests.factories import random_cloud


def _read(path: Path, labels: Path) -> list[np.ndarray]:
    chunks = list(
        iter_ascii_points(path, chunk_size=7_001, labels_path=labels, block_bytes=1 << 17)
    )
    return [
        np.concatenate([getattr(c, name) for c in chunks])
        for name in ("xyz", "intensity", "rgb", "labels")
    ]


def test_points_and_labels_read_the_same_on_any_thread_count(tmp_path: Path) -> None:
    cloud = random_cloud(60_000, seed=4, labels=True)
    points, labels = tmp_path / "scan.txt", tmp_path / "scan.labels"
    write_ascii_points(points, [cloud], labels_path=labels)
    results = []
    for n_threads in (1, 4):
        with thread_limit(n_threads):
            results.append((_read(points, labels), read_labels(labels)))
    (arrays_1, labels_1), (arrays_4, labels_4) = results
    assert all(np.array_equal(a, b) for a, b in zip(arrays_1, arrays_4, strict=True))
    assert np.array_equal(labels_1, labels_4)
    assert np.array_equal(labels_1, cloud.labels)
    assert np.array_equal(arrays_1[0], cloud.xyz)


def _general(path: Path) -> np.ndarray:
    return concatenate_arrays(list(_iter_label_blocks(path, 1 << 16)))


@pytest.mark.parametrize("shape", ["digits", "crlf", "wide_at_end", "no_final_newline"])
def test_large_label_files_read_as_the_checking_parser_reads_them(
    tmp_path: Path, shape: str
) -> None:
    values = np.random.default_rng(2).integers(0, 9, 700_000).astype(np.uint8)
    text = "\n".join(map(str, values.tolist())) + "\n"
    if shape == "crlf":
        text = text.replace("\n", "\r\n")
    elif shape == "wide_at_end":  # one-digit lines for most of the file, then a wider value
        text += "12\n"
    elif shape == "no_final_newline":
        text = text[:-1]
    path = tmp_path / "big.labels"
    path.write_text(text, newline="")
    expected = _general(path)
    assert np.array_equal(read_labels(path), expected)
    streamed = list(iter_labels(path, chunk_size=100_003))
    assert {chunk.size for chunk in streamed[:-1]} == {100_003}
    assert np.array_equal(np.concatenate(streamed), expected)


def test_a_bad_line_late_in_a_large_file_is_named(tmp_path: Path) -> None:
    path = tmp_path / "bad.labels"
    path.write_bytes(b"1\n" * 600_000 + b"x\n" + b"2\n" * 10)
    with pytest.raises(DataFormatError, match="line 600001"):
        read_labels(path)
    with pytest.raises(DataFormatError, match="line 600001"):
        list(iter_labels(path))


@pytest.mark.parametrize("n_threads", [1, 3])
@pytest.mark.parametrize("where", ["first", "middle", "last", "nowhere"])
def test_label_blocks_read_on_threads_equal_the_checking_parser(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, n_threads: int, where: str
) -> None:
    """Many pieces of many blocks on several threads: the same labels, and a block of
    another shape anywhere hands the whole file to the checking parser (values, or the
    bad line)."""
    from semantic3d.io import labels as labels_module

    monkeypatch.setattr(labels_module, "_PIECE_LABELS", 40_009)
    monkeypatch.setattr(labels_module, "_BLOCK_LINES", 1_001)
    values = np.random.default_rng(5).integers(0, 9, 400_000).astype(np.uint8)
    lines = [f"{v}\n".encode() for v in values.tolist()]
    at = {"first": 3, "middle": 211_111, "last": 399_998, "nowhere": None}[where]
    if at is not None:
        lines[at] = b"17\n"  # a wider value: another shape, not an error
        lines[at + 1] = b"\n"  # dropped to keep the size even; the checking parser refuses it
    path = tmp_path / "pieces.labels"
    path.write_bytes(b"".join(lines))
    with thread_limit(n_threads):
        if at is None:
            assert np.array_equal(read_labels(path), values)
            assert np.array_equal(read_labels(path), _general(path))
        else:
            with pytest.raises(DataFormatError, match=f"line {at + 2}"):
                read_labels(path)


def test_labels_without_positioned_reads_are_read_the_same(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Where the platform lacks ``os.pread`` (Windows) the file is streamed and parsed."""
    import os

    from semantic3d.io import _label_parsing

    values = np.random.default_rng(6).integers(0, 9, 700_000).astype(np.uint8)
    path = tmp_path / "turns.labels"
    path.write_bytes(b"".join(f"{v}\n".encode() for v in values.tolist()))

    def refuse(*args: object, **kwargs: object) -> bool:
        raise AssertionError("positioned reads where the platform has none")

    monkeypatch.delattr(os, "pread")
    monkeypatch.setattr(_label_parsing, "read_single_digit_file", refuse)
    with thread_limit(3):
        assert np.array_equal(read_labels(path), values)


def _digit_text(values: np.ndarray) -> bytearray:
    text = bytearray(2 * values.size)
    text[0::2] = (values.astype(np.uint8) + 48).tobytes()
    text[1::2] = b"\n" * values.size
    return text


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(0, 5_000),
    first=st.integers(0, 300),
    block_lines=st.integers(1, 700),
    n_threads=st.integers(1, 5),
    spoil=st.one_of(
        st.none(),
        st.tuples(
            st.floats(0, 1, exclude_max=True),  # where, as a share of the lines read
            st.sampled_from([b"x", b"\r", b":", b"/", b"9", b"\n"]),
            st.booleans(),  # the digit (True) or the line end
        ),
    ),
    seed=st.integers(0, 2**16),
)
# the digits' neighbours in the byte table, at a block's start, in a run's middle and on
# the last line
@example(n=3_000, first=10, block_lines=100, n_threads=3, spoil=(0.5, b":", True), seed=1)
@example(n=3_000, first=10, block_lines=100, n_threads=3, spoil=(0.0367, b"/", True), seed=2)
@example(n=3_000, first=0, block_lines=128, n_threads=4, spoil=(0.9999, b"\r", False), seed=3)
def test_the_file_reader_reads_every_line_or_says_it_could_not(
    n: int,
    first: int,
    block_lines: int,
    n_threads: int,
    spoil: tuple[float, bytes, bool] | None,
    seed: int,
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """The compiled reader, from line ``first``, in blocks split over runs: the values
    exactly when every line read is ``d\n`` (a line before ``first`` is not read)."""
    from semantic3d.io import _label_kernels as kernels

    values = np.random.default_rng(seed).integers(0, 10, first + n)
    text = _digit_text(values)
    good = True
    if spoil is not None and first + n:
        share, byte, digit = spoil
        line = int(share * (first + n))
        at = 2 * line + (0 if digit else 1)
        text[at : at + 1] = byte
        good = line < first or (byte == b"9" if digit else byte == b"\n")
    path = tmp_path_factory.mktemp("reader") / "scan.labels"
    path.write_bytes(text)
    out = np.full(n, 200, np.uint8)
    with path.open("rb", buffering=0) as stream:
        read = kernels.read_single_digit_file(stream.fileno(), first, out, block_lines, n_threads)
    assert read == good
    if good:
        expected = np.frombuffer(bytes(text), np.uint8)[0::2] - 48
        np.testing.assert_array_equal(out, expected[first:])


def test_the_file_reader_says_it_could_not_past_the_end(tmp_path: Path) -> None:
    path = tmp_path / "short.labels"
    path.write_bytes(_digit_text(np.full(5_000, 3)))
    with path.open("rb", buffering=0) as stream:
        for first, n in ((0, 5_001), (4_999, 2), (6_000, 1)):
            out = np.empty(n, np.uint8)
            assert not kernels_read(stream.fileno(), first, out)
        out = np.empty(5_000, np.uint8)
        assert kernels_read(stream.fileno(), 0, out)
    assert (out == 3).all()


def kernels_read(fd: int, first: int, out: np.ndarray) -> bool:
    from semantic3d.io import _label_kernels as kernels

    return bool(kernels.read_single_digit_file(fd, first, out, 777, 3))


def _window_rows(
    text: bytes, n_segments: int, n_threads: int, room: int
) -> tuple[int, int, int, np.ndarray]:
    from semantic3d.io import _ascii_kernels as kernels

    buf = np.frombuffer(text + bytes(kernels.FAST_MARGIN), np.uint8)
    rows = text.count(b"\n")
    xyz = np.full((rows, 3), np.nan)
    intensity, rgb = np.zeros(rows, np.int32), np.zeros((rows, 3), np.uint8)
    slow = np.empty((n_segments, 128, 4), np.int64)
    state = np.zeros((n_segments, kernels.STATE_SIZE), np.int64)
    n_lines, used, end = kernels.parse_window(
        buf,
        buf.size,
        0,
        len(text),
        n_segments,
        0,
        room,
        xyz,
        intensity,
        rgb,
        slow,
        state,
        n_threads,
    )
    assert not state[:used, kernels.STATE_STATUS].any()
    ends = state[:used, kernels.STATE_END]
    assert (np.diff(ends) >= 0).all() and ends[-1] == end  # segments in order, none crossing
    return int(n_lines), int(used), int(end), xyz[: int(n_lines)]


@settings(max_examples=60, deadline=None)
@given(
    widths=st.lists(st.integers(0, 60), min_size=1, max_size=80),
    n_segments=st.integers(1, 120),
    n_threads=st.integers(1, 4),
    room=st.integers(1, 100),
)
def test_a_window_parses_the_same_in_any_number_of_segments(
    widths: list[int], n_segments: int, n_threads: int, room: int
) -> None:
    """Segments cut where their equal byte ranges begin a line: lines of any length (some
    longer than a segment, so that several segments start on one line and hold none),
    more segments than lines, and the window cut after ``room`` lines."""
    lines = [f"{i} {'1' * (w + 1)} -2.5 7 1 2 3\n".encode() for i, w in enumerate(widths)]
    text = b"".join(lines)
    n_lines, _, end, xyz = _window_rows(text, n_segments, n_threads, room)
    whole = _window_rows(text, 1, 1, room)
    assert n_lines == min(room, len(lines)) == whole[0]
    assert end == len(b"".join(lines[:n_lines])) == whole[2]
    assert np.array_equal(xyz, whole[3], equal_nan=True)  # wide values are deferred: NaN
    assert xyz[:, 0].tolist() == list(range(n_lines))
