"""The Python parser of small point files against the compiled kernels, on the same files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.errors import DataFormatError
from semantic3d.io import _point_text
from semantic3d.io._point_reader import iter_point_batches
from semantic3d.io.ascii import iter_ascii_points

_TOKENS = ["0", "-0", "12.345", "-1515", "255", "256", "-1", "1.5", "+.5", "1.", "1e5",
           "1e400", "-1e400", "1e-400", "0e99999", "1e30", "2.5e-3", "12345678901234567",
           "1.00000000000000001", "3000000000", "1e", "abc", "--1", "1.2.3", "."]  # fmt: skip
_BLANKS = [" ", " ", " ", "\t", "  ", " \r"]


@st.composite
def point_texts(draw: st.DrawFn) -> bytes:
    lines = []
    for _ in range(draw(st.integers(0, 6))):
        n_tokens = draw(st.sampled_from([7, 7, 7, 6, 8, 0]))
        tokens = [draw(st.sampled_from(_TOKENS)) for _ in range(n_tokens)]
        line = draw(st.sampled_from(["", " ", "\t"])) + "".join(
            token + (draw(st.sampled_from(_BLANKS)) if i < n_tokens - 1 else "")
            for i, token in enumerate(tokens)
        )
        lines.append(line + draw(st.sampled_from(["", "", " ", "\r"])))
    end = draw(st.sampled_from(["\n", "\r\n"]))
    return (end.join(lines) + draw(st.sampled_from(["", end]))).encode()


def _outcome(chunks: object) -> object:
    try:
        clouds = list(chunks)  # type: ignore[call-overload]
    except DataFormatError as exc:
        return str(exc)
    return [(c.xyz.tobytes(), c.intensity.tolist(), c.rgb.tolist()) for c in clouds]


@settings(max_examples=40, deadline=None)
@given(data=point_texts(), chunk_size=st.integers(1, 4))
def test_the_small_file_parser_equals_the_kernels(
    data: bytes, chunk_size: int, tmp_path_factory: pytest.TempPathFactory
) -> None:
    path = tmp_path_factory.getbasetemp() / "scan.txt"
    path.write_bytes(data)
    small = _outcome(_point_text.iter_small_points(path, data, chunk_size))
    assert small == _outcome(iter_point_batches(path, chunk_size, 1 << 16))
    assert small == _outcome(iter_ascii_points(path, chunk_size=chunk_size))


def test_a_file_past_the_threshold_goes_to_the_kernels(tmp_path: Path) -> None:
    line = b"1.000 2.000 3.000 -5 1 2 3\n"
    large = tmp_path / "large.txt"
    n_lines = _point_text.SMALL_FILE_BYTES // len(line) + 1
    large.write_bytes(line * n_lines + b"1 2 3\n")
    with pytest.raises(DataFormatError, match=f"line {n_lines + 1}: expected 7 columns"):
        list(iter_ascii_points(large))
    with pytest.raises(DataFormatError, match=f"line {n_lines + 1}: expected 7 columns"):
        list(_point_text.iter_small_points(large, large.read_bytes(), 1 << 20))


def test_the_deferred_token_rule_follows_the_kernels() -> None:
    deferred = _point_text._deferred
    assert not deferred(b"123456789012345") and deferred(b"1234567890123456")
    assert deferred(b"0.000000000000000000000000000001e5")  # exponent 5 - 30
    assert not deferred(b"0.000000000000000000000000000000e99")  # zero: exact
    assert deferred(b"1e23") and not deferred(b"1e22") and not deferred(b"1.5e23")
    assert not deferred(b"0e999999") and deferred(b"1E-23") and not deferred(b"00001e-22")
    values = np.array([float(t) for t in ("1.5e23", "0e999999")])
    assert values.tolist() == [1.5e23, 0.0]
