"""The point parser's numbers against Python's ``float()``, bit for bit, and its framing.

Every accepted numeric shape must give exactly the double ``float(token)`` gives: the
SWAR fast path (``-12.345``), the exact integer-over-power-of-ten path (up to 15
significant digits, exponents within ±22) and the deferred general path (17 digits,
large exponents).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core import DataFormatError, PointCloud
from semantic3d.io import _point_text, iter_ascii_points, read_ascii_points


def _bits(values: np.ndarray) -> list[int]:
    return np.asarray(values, np.float64).view(np.uint64).tolist()


def _read_tokens(folder: Path, tokens: list[str], separator: str = " ") -> np.ndarray:
    """Read ``tokens`` as x (and as y, z with other neighbours) and return all three columns."""
    lines = [
        separator.join([token, tokens[(i + 1) % len(tokens)], "-0.5", "7", "1", "2", "3"])
        for i, token in enumerate(tokens)
    ]
    path = folder / "numbers.txt"
    path.write_text("\n".join(lines) + "\n")
    cloud = read_ascii_points(path)
    assert cloud.n_points == len(tokens)
    return cloud.xyz


def _assert_exact(folder: Path, tokens: list[str]) -> None:
    xyz = _read_tokens(folder, tokens)
    assert _bits(xyz[:, 0]) == _bits([float(t) for t in tokens]), tokens
    shifted = [tokens[(i + 1) % len(tokens)] for i in range(len(tokens))]
    assert _bits(xyz[:, 1]) == _bits([float(t) for t in shifted])


ADVERSARIAL = [
    "0", "-0", "0.0", "-0.000", "+0", "5.", ".5", "-.5", "+.5", "1e0", "1E+0", "-1e-0",
    "0.1", "0.2", "0.3", "-12.345", "-1515", "255", "3.772", "-16.070", "870277.390",
    "6618000.125", "9999999", "99999999", "12345678.9", "1234567.1234567",
    "9007199254740992", "9007199254740993", "123456789012345", "1234567890123456",
    "0.30000000000000004", "2.2250738585072014e-308", "4.9e-324", "5e-324", "2e-324",
    "1.7976931348623157e308", "1e22", "1e23", "1e-22", "1e-23", "123456789012345e-22",
    "123456789012345e22", "8.98846567431158e307", "0.000000000000000000000000001",
    "1" + "0" * 40, "0." + "0" * 40 + "1", "3." + "1" * 30, "1e-400", "-1e-400",
    "0e999", "000000000000000000000000000123.5", "1.00000000000000000000000000000001",
    "2.5e-3", "12.5e2", "0.1e1", "7.e3", "-00.0100",
]  # fmt: skip


def test_adversarial_shapes_equal_python_float(tmp_path: Path) -> None:
    _assert_exact(tmp_path, ADVERSARIAL)


def test_every_fast_shape_equals_python_float(tmp_path: Path) -> None:
    """All sign/integer-digits/fraction-digits combinations of the fast paths."""
    rng = np.random.default_rng(5)
    tokens = []
    for sign in ("", "-"):
        for n_whole in range(0, 9):
            for n_fraction in range(-1, 9):  # -1: no point at all
                if n_whole == 0 and n_fraction <= 0:
                    continue
                for _ in range(6):
                    whole = "".join(rng.choice(list("0123456789"), n_whole))
                    text = sign + whole
                    if n_fraction >= 0:
                        text += "." + "".join(rng.choice(list("0123456789"), n_fraction))
                    tokens.append(text)
    _assert_exact(tmp_path, tokens)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=1, max_size=40))
def test_shortest_repr_of_any_double_round_trips(
    tmp_path_factory: pytest.TempPathFactory, values: list[float]
) -> None:
    tokens = (
        [repr(v) for v in values] + [f"{v:.17g}" for v in values] + [f"{v:.3e}" for v in values]
    )
    tokens = [t for t in tokens if np.isfinite(float(t))]  # 1.7975e308 rounds to 1.798e+308
    _assert_exact(tmp_path_factory.mktemp("repr"), tokens)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["", "-", "+"]),
            st.text("0123456789", min_size=0, max_size=20),
            st.one_of(st.none(), st.text("0123456789", min_size=0, max_size=20)),
            st.one_of(st.none(), st.integers(-330, 330)),
        ),
        min_size=1,
        max_size=30,
    )
)
def test_random_decimal_shapes_equal_python_float(
    tmp_path_factory: pytest.TempPathFactory,
    parts: list[tuple[str, str, str | None, int | None]],
) -> None:
    tokens = []
    for sign, whole, fraction, exponent in parts:
        text = sign + whole + ("" if fraction is None else "." + fraction)
        if not (whole or fraction):
            continue
        if exponent is not None:
            text += f"e{exponent}"
        if np.isfinite(float(text)):
            tokens.append(text)
    if tokens:
        _assert_exact(tmp_path_factory.mktemp("shapes"), tokens)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, 2**64 - 1), min_size=1, max_size=50))
def test_random_bit_patterns_round_trip(
    tmp_path_factory: pytest.TempPathFactory, patterns: list[int]
) -> None:
    values = [struct.unpack("<d", struct.pack("<Q", bits))[0] for bits in patterns]
    tokens = [repr(v) for v in values if np.isfinite(v)]
    if tokens:
        _assert_exact(tmp_path_factory.mktemp("bits"), tokens)


def test_many_deferred_tokens_pause_and_resume(tmp_path: Path) -> None:
    """More 17-digit tokens than a segment's deferred list holds, across windows."""
    rng = np.random.default_rng(11)
    values = rng.uniform(-1e3, 1e3, (30_000, 3))
    lines = [f"{x!r} {y!r} {z!r} 1 2 3 4" for x, y, z in values.tolist()]
    path = tmp_path / "long.txt"
    path.write_text("\n".join(lines) + "\n")
    for block_bytes in (1 << 20, 50_000):
        xyz = np.concatenate(
            [c.xyz for c in iter_ascii_points(path, chunk_size=7_000, block_bytes=block_bytes)]
        )
        assert _bits(xyz.ravel()) == _bits(values.ravel())


def test_integers_in_any_accepted_shape(tmp_path: Path) -> None:
    path = tmp_path / "ints.txt"
    path.write_text(
        "0 0 0 -2147483648 0 255 -0\n"
        "0 0 0 2147483647 1e2 2.55e2 +7\n"
        "0 0 0 4.000 1.0000000000000000000000 25500e-2 0000255\n"
    )
    cloud = read_ascii_points(path)
    assert cloud.intensity.tolist() == [-2147483648, 2147483647, 4]
    assert cloud.rgb.tolist() == [[0, 255, 0], [100, 255, 7], [1, 255, 255]]


INTEGER_TOKENS = [
    "0", "-0", "7", "-7", "+7", "255", "256", "0000255", "-0000", "1234567", "12345678",
    "-1234567", "2147483647", "2147483648", "-2147483648", "-", "7e", "7.0", "07", "1e2",
]  # fmt: skip


def _row_or_problem(path: Path, row: int) -> tuple[object, ...]:
    try:
        cloud = read_ascii_points(path)
    except DataFormatError as exc:
        return ("problem", str(exc).split(": line ")[-1].split(": ", 1)[-1])
    return (cloud.intensity[row].item(), cloud.rgb[row].tolist())


@pytest.mark.parametrize("column", [3, 4, 5, 6])
def test_integer_tokens_read_alike_by_every_path(tmp_path: Path, column: int) -> None:
    """An integer token gives the same value or the same problem whichever path reads
    its line: the compiled fast path (a large file, many lines after it), the compiled
    general path (a large file's last line) and the small-file parser; in the intensity
    and in each colour column."""
    ordinary = "1.000 2.000 3.000 4 5 6 7\n"
    n_ordinary = _point_text.SMALL_FILE_BYTES // len(ordinary) + 1
    for token in INTEGER_TOKENS:
        fields = ["-1.250", "2.500", "3.750", "9", "10", "11", "12"]
        fields[column] = token
        line = " ".join(fields) + "\n"
        fast, general, small = (tmp_path / f"{name}.txt" for name in ("fast", "general", "small"))
        fast.write_text(line + ordinary * n_ordinary)
        general.write_text(ordinary * n_ordinary + line)
        small.write_text(line)
        expected = _row_or_problem(small, 0)
        assert _row_or_problem(fast, 0) == expected, token
        assert _row_or_problem(general, n_ordinary) == expected, token


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("1e400 2 3 4 5 6 7", r"line 2: expected finite numbers .*found '1e400'"),
        ("1 -1e309 3 4 5 6 7", r"line 2: expected finite numbers .*found '-1e309'"),
        ("1 2 " + "9" * 400 + " 4 5 6 7", r"line 2: expected finite numbers"),
        ("inf 2 3 4 5 6 7", r"line 2: expected numbers in every column, found 'inf'"),
        ("1 -infinity 3 4 5 6 7", r"line 2: expected numbers in every column, found '-infinity'"),
        ("1 2 NaN 4 5 6 7", r"line 2: expected numbers in every column, found 'NaN'"),
        ("1 2 3 1e400 5 6 7", r"line 2: expected finite numbers .*found '1e400'"),
        ("1 2 3 2147483648 5 6 7", r"line 2: expected r g b in 0\.\.255 and an int32"),
        ("1 2 3 4 5 6 1e300", r"line 2: expected r g b in 0\.\.255"),
        ("1 2 3 4 5 6 2.5500000000001e2", r"line 2: expected integer intensity"),
        ("1 2 3 4.5e0 5 6 7", r"line 2: expected integer intensity .*found '4\.5e0'"),
        ("1 2 3 4 5 6 7e", r"line 2: expected numbers in every column, found '7e'"),
        ("1 2 3 4 5 6 .", r"line 2: expected numbers in every column, found '\.'"),
        ("1 2 3 4 5 6 -", r"line 2: expected numbers in every column, found '-'"),
        ("1 2 3 4 5 6 1_0", r"line 2: expected numbers in every column, found '1_0'"),
        ("1 2 3 4 5 6 0x10", r"line 2: expected numbers in every column, found '0x10'"),
        ("1 2 3 4 5 6 1.2.3", r"line 2: expected numbers in every column, found '1\.2\.3'"),
        ("1 2 3 4 5 6 --1", r"line 2: expected numbers in every column, found '--1'"),
        ("1 2 3 4 5 6 7\r8", r"line 2: expected 7 columns"),
        ("1 2 3 4 5 6 7 \t ", None),
    ],
)
def test_non_finite_and_malformed_tokens(tmp_path: Path, line: str, message: str | None) -> None:
    path = tmp_path / "scan.txt"
    path.write_text("1 2 3 4 5 6 7\n" + line + "\n0 0 0 0 0 0 0\n")
    if message is None:
        assert read_ascii_points(path).n_points == 3
        return
    with pytest.raises(DataFormatError, match=message):
        read_ascii_points(path)


def test_the_first_problem_in_file_order_is_reported(tmp_path: Path) -> None:
    """A deferred-token problem (found after the kernel) before a kernel problem."""
    good = "1.000 2.000 3.000 4 5 6 7\n"
    path = tmp_path / "scan.txt"
    path.write_text(good * 3000 + "1e999 0 0 0 0 0 0\n" + good * 3000 + "1 2 3\n" + good)
    with pytest.raises(DataFormatError, match="line 3001: expected finite"):
        read_ascii_points(path)
    path.write_text(good * 3000 + "1 2 3\n" + good * 3000 + "1e999 0 0 0 0 0 0\n")
    with pytest.raises(DataFormatError, match="line 3001: expected 7 columns"):
        read_ascii_points(path)


FRAMING = {
    "one line": ("1.5 2 3 4 5 6 7\n", 1),
    "one line without newline": ("1.5 2 3 4 5 6 7", 1),
    "zero lines": ("", 0),
    "crlf": ("1.5 2 3 4 5 6 7\r\n" * 3, 3),
    "crlf without final": ("1.5 2 3 4 5 6 7\r\n1.5 2 3 4 5 6 7", 2),
    "tabs and blanks": ("\t1.5 \t2  3 4 5 6 7 \r\n", 1),
}


@pytest.mark.parametrize("name", sorted(FRAMING))
def test_framing(tmp_path: Path, name: str) -> None:
    text, n = FRAMING[name]
    path = tmp_path / "scan.txt"
    path.write_bytes(text.encode())
    cloud = read_ascii_points(path)
    assert cloud.n_points == n
    if n:
        assert cloud.xyz[0].tolist() == [1.5, 2.0, 3.0]
        assert cloud.intensity.tolist() == [4] * n
        assert cloud.rgb.tolist() == [[5, 6, 7]] * n


def test_a_line_that_is_not_text_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "binary.txt"
    path.write_bytes(b"1" * (2 << 20))
    with pytest.raises(DataFormatError, match="line longer than"):
        read_ascii_points(path)
    path.write_bytes(b"1 2 3 4 5 6 7\n" + b"1" * (2 << 20) + b"\n")
    with pytest.raises(DataFormatError, match="line longer than"):
        list(iter_ascii_points(path, block_bytes=4096))


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 400),
    seed=st.integers(0, 2**16),
    chunk_size=st.integers(1, 150),
    block_bytes=st.integers(1, 3000),
    crlf=st.booleans(),
    final_newline=st.booleans(),
)
def test_windows_and_chunks_split_anywhere(
    tmp_path_factory: pytest.TempPathFactory,
    n: int,
    seed: int,
    chunk_size: int,
    block_bytes: int,
    crlf: bool,
    final_newline: bool,
) -> None:
    """Windows that end inside lines and chunks of any size give the one-shot result."""
    rng = np.random.default_rng(seed)
    xyz = np.round(rng.normal(0, 100, (n, 3)), int(rng.integers(0, 6)))
    intensity = rng.integers(-3000, 3000, n)
    rgb = rng.integers(0, 256, (n, 3))
    end = "\r\n" if crlf else "\n"
    lines = [
        f"{x!r} {y} {z:.4f} {i} {r} {g} {b}"
        for (x, y, z), i, (r, g, b) in zip(xyz.tolist(), intensity, rgb.tolist(), strict=True)
    ]
    text = end.join(lines) + (end if final_newline and lines else "")
    path = tmp_path_factory.mktemp("frames") / "scan.txt"
    path.write_text(text, newline="")
    whole = read_ascii_points(path)
    expected = PointCloud.from_arrays(
        [[float(t) for t in line.split()[:3]] for line in lines] if lines else np.empty((0, 3)),
        intensity=intensity,
        rgb=rgb,
    )
    assert whole.equals(expected)
    chunks = list(iter_ascii_points(path, chunk_size=chunk_size, block_bytes=block_bytes))
    assert [c.n_points for c in chunks[:-1]] == [chunk_size] * (len(chunks) - 1)
    assert sum(c.n_points for c in chunks) == n
    if chunks:
        assert PointCloud.concatenate(chunks).equals(whole)


def test_a_pipe_is_read_in_blocks(tmp_path: Path) -> None:
    """Files that cannot be memory-mapped (a FIFO) take the block reader."""
    import os
    import threading

    fifo = tmp_path / "scan.fifo"
    os.mkfifo(fifo)
    text = "1.5 2 3 4 5 6 7\n" * 50_000 + "1 2 3 4 5 6 8"

    def feed() -> None:
        with fifo.open("w") as stream:
            stream.write(text)

    thread = threading.Thread(target=feed)
    thread.start()
    cloud = read_ascii_points(fifo)
    thread.join()
    assert cloud.n_points == 50_001
    assert cloud.rgb[-1].tolist() == [5, 6, 8]
