from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core import DataFormatError, PointCloud
from semantic3d.io import (
    iter_ascii_points,
    open_ascii_writer,
    read_ascii_points,
    write_ascii_points,
)
from semantic3d.io.labels import format_labels_bytes
from tests.factories import random_cloud
from tests.mappings import mapped_kib


def _write(tmp_path: Path, text: str, name: str = "scan.txt") -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode())
    return path


def test_reads_the_benchmark_line_format(tmp_path: Path) -> None:
    path = _write(tmp_path, "-5.387 13.654 -1.742 -1515 92 86 72\n1 2 3 0 255 0 1\n")
    cloud = read_ascii_points(path)
    assert cloud.xyz.tolist() == [[-5.387, 13.654, -1.742], [1.0, 2.0, 3.0]]
    assert cloud.intensity.tolist() == [-1515, 0]
    assert cloud.rgb.tolist() == [[92, 86, 72], [255, 0, 1]]
    assert cloud.labels is None


@pytest.mark.parametrize(
    "text",
    [
        "1.5 2 3 4 5 6 7\r\n8 9 10 11 12 13 14\r\n",  # CRLF
        "1.5 2 3 4 5 6 7\n8 9 10 11 12 13 14",  # no final newline
        "1.5 2 3 4 5 6 7   \n8\t9 10 11 12 13 14 \t\n",  # trailing blanks, tabs
        "  1.5  2 3 4 5 6 7\n+8 9e0 1.0e1 11 12 13 14\n",  # leading blanks, signs, exponents
    ],
)
def test_tolerated_variants(tmp_path: Path, text: str) -> None:
    cloud = read_ascii_points(_write(tmp_path, text))
    assert cloud.xyz.tolist() == [[1.5, 2, 3], [8, 9, 10]]
    assert cloud.intensity.tolist() == [4, 11]
    assert cloud.rgb.tolist() == [[5, 6, 7], [12, 13, 14]]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "1 2 3 4 5 6 7\n1 2 3 4\n",
            r"scan\.txt: line 2: expected 7 columns \(x y z intensity r g b\), found 4",
        ),
        ("1 2 3 4 5 6 7 8\n", r"line 1: expected 7 columns \(x y z intensity r g b\), found 8"),
        ("1 2 3 4 5 6 7\n\n", r"line 2: expected 7 columns .*, found 0"),
        ("1 2 abc 4 5 6 7\n", r"line 1: expected numbers in every column, found 'abc'"),
        ("1 2 3,5 4 5 6 7\n", r"line 1: expected numbers in every column, found '3,5'"),
        ("1 2 nan 4 5 6 7\n", r"line 1: expected numbers in every column, found 'nan'"),
        ("1 2 3 4 5 6 256\n", r"line 1: expected r g b in 0\.\.255 .*found '4 5 6 256'"),
        ("1 2 3 4 -1 6 7\n", r"line 1: expected r g b in 0\.\.255"),
        (
            "1 2 3 4.5 5 6 7\n",
            r"line 1: expected integer intensity and colour values, found '4\.5'",
        ),
        (
            "1 2 3 4 5 6.2 7\n",
            r"line 1: expected integer intensity and colour values, found '6\.2'",
        ),
    ],
)
def test_bad_lines_name_file_line_expected_and_found(
    tmp_path: Path, text: str, message: str
) -> None:
    with pytest.raises(DataFormatError, match=message):
        read_ascii_points(_write(tmp_path, text))


def test_error_line_numbers_across_blocks_and_segments(tmp_path: Path) -> None:
    good = "1.000 2.000 3.000 4 5 6 7\n"
    path = _write(tmp_path, good * 5000 + "1 2 3\n" + good * 10)
    with pytest.raises(DataFormatError, match="line 5001: expected 7 columns"):
        list(iter_ascii_points(path, block_bytes=1000))
    with pytest.raises(DataFormatError, match="line 5001: expected 7 columns"):
        read_ascii_points(path)


def test_numbers_parse_exactly_like_python(tmp_path: Path) -> None:
    """Every shape equals float(), 17-digit repr output included (bit for bit)."""
    rng = np.random.default_rng(3)
    values = np.concatenate(
        [
            rng.uniform(-1e6, 1e6, 3000),
            rng.normal(0, 1e-3, 3000),
            np.round(rng.uniform(-1000, 1000, 3000), 3),
        ]
    ).reshape(-1, 3)
    lines = [f"{x:.15g} {y:.6f} {z:.3e} 0 0 0 0" for x, y, z in values]
    cloud = read_ascii_points(_write(tmp_path, "\n".join(lines) + "\n"))
    expected = np.array([[float(t) for t in line.split()[:3]] for line in lines])
    np.testing.assert_array_equal(cloud.xyz, expected)

    long_lines = [f"{float(x)!r} {float(y)!r} {float(z)!r} 0 0 0 0" for x, y, z in values]
    cloud = read_ascii_points(_write(tmp_path, "\n".join(long_lines) + "\n", "long.txt"))
    np.testing.assert_array_equal(cloud.xyz.view(np.uint64), values.view(np.uint64))


def test_georeferenced_coordinates_keep_millimetres(tmp_path: Path) -> None:
    cloud = random_cloud(1000, offset=870_000.0)
    path = tmp_path / "geo.txt"
    write_ascii_points(path, [cloud])
    back = read_ascii_points(path)
    assert np.abs(back.xyz - cloud.xyz).max() < 1e-6


def test_points_and_labels_stream_together(tmp_path: Path) -> None:
    cloud = random_cloud(2500)
    points, labels = tmp_path / "s.txt", tmp_path / "s.labels"
    assert write_ascii_points(points, [cloud[:1000], cloud[1000:]], labels_path=labels) == 2500
    chunks = list(iter_ascii_points(points, chunk_size=1000, labels_path=labels, block_bytes=4096))
    assert [c.n_points for c in chunks] == [1000, 1000, 500]
    assert PointCloud.concatenate(chunks).equals(cloud)


def test_label_count_mismatch_is_reported(tmp_path: Path) -> None:
    cloud = random_cloud(100)
    points, labels = tmp_path / "s.txt", tmp_path / "s.labels"
    write_ascii_points(points, [cloud], labels_path=labels)
    labels.write_bytes(b"1\n" * 99)
    with pytest.raises(DataFormatError, match=r"s\.labels: expected one label per point of s\.txt"):
        read_ascii_points(points, labels_path=labels)
    labels.write_bytes(b"1\n" * 101)
    with pytest.raises(DataFormatError, match=r"\(100 points\), found 101 labels"):
        read_ascii_points(points, labels_path=labels)


def test_writer_is_deterministic_and_rounds_to_decimals(tmp_path: Path) -> None:
    cloud = PointCloud.from_arrays(
        [[-0.0004, 1.23456, -2.5], [1e6 + 0.0005, -1.0, 0.0]],
        intensity=[-1515, 7],
        rgb=[[0, 1, 2], [253, 254, 255]],
    )
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    write_ascii_points(a, [cloud])
    with open_ascii_writer(b) as writer:
        writer.write(cloud[:1])
        writer.write(cloud[1:])
    assert a.read_bytes() == b.read_bytes()
    assert a.read_text().splitlines() == [
        "0.000 1.235 -2.500 -1515 0 1 2",
        "1000000.000 -1.000 0.000 7 253 254 255",
    ]
    write_ascii_points(a, [cloud], decimals=0)
    assert a.read_text().splitlines()[0] == "0 1 -2 -1515 0 1 2"


def test_writer_rejects_non_finite_coordinates(tmp_path: Path) -> None:
    cloud = PointCloud.from_arrays([[0, 0, 0], [np.nan, 0, 0]])
    with pytest.raises(DataFormatError, match=r"point #1: expected finite coordinates"):
        write_ascii_points(tmp_path / "bad.txt", [cloud])


def test_writer_names_a_bad_point_by_its_place_in_the_file_and_writes_nothing(
    tmp_path: Path,
) -> None:
    cloud = random_cloud(300_000, labels=True)
    cloud.xyz[200_001, 2] = np.inf  # in the second formatting batch of the second chunk
    cloud.xyz[250_000, 0] = 1e17  # beyond what 3 decimals hold in 64 bits
    points, labels = tmp_path / "a.txt", tmp_path / "a.labels"
    with (
        pytest.raises(DataFormatError, match=r"point #200001: expected finite coordinates below"),
        open_ascii_writer(points, labels_path=labels) as writer,
    ):
        writer.write(cloud[:50_000])
        writer.write(cloud[50_000:])
    assert list(tmp_path.iterdir()) == []
    cloud.xyz[200_001, 2] = 0.0
    with pytest.raises(DataFormatError, match=r"point #250000: expected finite coordinates below"):
        write_ascii_points(points, [cloud], labels_path=labels)


def test_writer_counts_the_labels_it_writes(tmp_path: Path) -> None:
    cloud = random_cloud(200_000, labels=True)
    cloud.labels[:7] = [255, 10, 99, 100, 0, 9, 200]
    with open_ascii_writer(tmp_path / "a.txt", labels_path=tmp_path / "a.labels") as writer:
        writer.write(cloud)
    np.testing.assert_array_equal(writer.label_counts, np.bincount(cloud.labels, minlength=256))
    assert (tmp_path / "a.labels").read_bytes() == format_labels_bytes(cloud.labels).tobytes()


def test_writer_needs_labels_when_given_a_labels_path(tmp_path: Path) -> None:
    with (
        pytest.raises(DataFormatError, match="expected points with labels"),
        open_ascii_writer(tmp_path / "a.txt", labels_path=tmp_path / "a.labels") as writer,
    ):
        writer.write(random_cloud(3, labels=False))


def test_real_samples_match_a_reference_parser(shared_data: Path) -> None:
    for path in sorted(shared_data.glob("*/*.txt")):
        cloud = read_ascii_points(path, labels_path=path.with_suffix(".labels"))
        reference = np.loadtxt(path, max_rows=2000)
        np.testing.assert_array_equal(cloud.xyz[:2000], reference[:, :3])
        np.testing.assert_array_equal(cloud.intensity[:2000], reference[:, 3])
        np.testing.assert_array_equal(cloud.rgb[:2000], reference[:, 4:])
        assert cloud.labels is not None and cloud.labels.size == cloud.n_points


def test_real_georeferenced_sample_round_trips_to_the_millimetre(
    shared_data: Path, tmp_path: Path
) -> None:
    source = shared_data / "ign-lidarhd-toy" / "870000_6618000_subset.txt"
    cloud = read_ascii_points(source)
    assert cloud.xyz[:, 0].min() > 869_000
    out = tmp_path / "copy.txt"
    write_ascii_points(out, iter_ascii_points(source, chunk_size=10_000))
    assert out.read_bytes() == source.read_bytes()


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 300),
    seed=st.integers(0, 2**16),
    chunk_size=st.integers(1, 120),
    block_bytes=st.integers(64, 2000),
)
def test_round_trip_and_chunked_equals_whole(
    tmp_path_factory: pytest.TempPathFactory, n: int, seed: int, chunk_size: int, block_bytes: int
) -> None:
    cloud = random_cloud(n, seed=seed, offset=float(seed))
    folder = tmp_path_factory.mktemp("ascii")
    points, labels = folder / "r.txt", folder / "r.labels"
    write_ascii_points(points, [cloud], labels_path=labels)
    whole = read_ascii_points(points, labels_path=labels)
    assert whole.equals(cloud)
    chunks = list(
        iter_ascii_points(
            points, chunk_size=chunk_size, labels_path=labels, block_bytes=block_bytes
        )
    )
    assert all(c.n_points == chunk_size for c in chunks[:-1])
    assert PointCloud.concatenate(chunks).equals(cloud) or n == 0


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="Linux's mapping table")
def test_pages_behind_the_cursor_leave_the_mapping(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Resident memory does not grow with the file: halfway through a mapped scan, the
    pages already parsed are no longer this process's (they stay in the page cache)."""
    import semantic3d.io._point_reader as reader

    monkeypatch.setattr(reader, "_RELEASE_BYTES", 256 << 10)  # steps of 256 KiB
    cloud = random_cloud(150_000, seed=8)
    path = tmp_path / "scan.txt"
    write_ascii_points(path, [cloud])
    size_kib = path.stat().st_size // 1024
    assert size_kib > 4_000
    chunks = iter_ascii_points(path, chunk_size=1 << 16, block_bytes=64 << 10)
    read, resident = 0, []
    for chunk in chunks:
        read += chunk.n_points
        resident.append(mapped_kib(path))
    assert read == cloud.n_points
    assert max(resident) > 0, "the scan was read through a mapping"
    # a step or two ahead of the cursor and the batch being parsed, not the half read
    assert max(resident[len(resident) // 3 :]) < size_kib // 4


def test_a_scan_is_read_where_pages_cannot_be_advised(tmp_path: Path) -> None:
    """Where the C library has no ``madvise`` (Windows), the parser's kernels still
    compile (the symbol is bound to a function that does nothing) and read the same."""
    cloud = random_cloud(60_000, seed=9)
    path = tmp_path / "scan.txt"
    write_ascii_points(path, [cloud])
    code = (
        "import mmap, sys\n"
        "for name in [n for n in dir(mmap) if n.startswith('MADV_')]:\n"
        "    delattr(mmap, name)\n"
        "import numpy as np\n"
        "from semantic3d.io import iter_ascii_points\n"
        "import semantic3d.io._page_advice as advice\n"
        "assert advice.DROP_ADVICE == 0\n"
        "chunks = list(iter_ascii_points(sys.argv[1], block_bytes=1 << 16))\n"
        "np.save(sys.argv[2], np.concatenate([c.xyz for c in chunks]))\n"
    )
    saved = tmp_path / "xyz.npy"
    subprocess.run([sys.executable, "-c", code, str(path), str(saved)], check=True)
    assert np.array_equal(np.load(saved), cloud.xyz)
