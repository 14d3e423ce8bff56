"""Reading gives the same arrays on any number of threads (segments, windows and pieces
split differently), and large ``.labels`` read by the fast path equal the checking parser's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

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
def test_label_pieces_read_on_threads_equal_the_checking_parser(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, n_threads: int, where: str
) -> None:
    """Many pieces on several threads: the same labels, and a piece of another shape
    anywhere hands the whole file to the checking parser (values, or the bad line)."""
    from semantic3d.io import labels as labels_module

    monkeypatch.setattr(labels_module, "_PIECE_LABELS", 40_009)
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


def test_label_pieces_without_positioned_reads_take_turns_and_read_the_same(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Where the platform lacks ``os.preadv`` (Windows) the threads seek in turn."""
    import os

    from semantic3d.io import labels as labels_module

    monkeypatch.setattr(labels_module, "_PIECE_LABELS", 30_011)
    values = np.random.default_rng(6).integers(0, 9, 300_000).astype(np.uint8)
    path = tmp_path / "turns.labels"
    path.write_bytes(b"".join(f"{v}\n".encode() for v in values.tolist()))
    monkeypatch.delattr(os, "preadv")
    with thread_limit(3):
        assert np.array_equal(read_labels(path), values)
