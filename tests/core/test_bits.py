"""The compiled bit operations: what they return, against plain Python on the same words."""

from __future__ import annotations

import numba as nb
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.bits import CHANGE_SPAN, bit_count, trailing_zeros, word_changes


@nb.njit(cache=False)
def _counts(word: np.uint64) -> tuple[int, int]:
    return trailing_zeros(word), bit_count(word)


@nb.njit(cache=False)
def _changes(first: np.ndarray, second: np.ndarray, at: int) -> np.uint64:
    return word_changes(first, second, at)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**64 - 1))
def test_trailing_zeros_and_bit_count_are_those_of_the_word(word: int) -> None:
    zeros, count = _counts(np.uint64(word))
    assert zeros == (64 if word == 0 else (word & -word).bit_length() - 1)
    assert count == bin(word).count("1")


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.integers(0, 3), min_size=CHANGE_SPAN + 1, max_size=3 * CHANGE_SPAN),
    st.lists(st.integers(0, 3), min_size=CHANGE_SPAN + 1, max_size=3 * CHANGE_SPAN),
    st.data(),
)
def test_word_changes_marks_the_words_that_differ_from_the_next_in_either_array(
    first: list[int], second: list[int], data: st.DataObject
) -> None:
    n = min(len(first), len(second))
    at = data.draw(st.integers(0, n - CHANGE_SPAN - 1))
    a = np.array(first[:n], np.uint16) * np.uint16(0x1001)  # high and low bytes both vary
    b = np.array(second[:n], np.uint16)
    expected = sum(
        1 << j
        for j in range(CHANGE_SPAN)
        if a[at + j] != a[at + j + 1] or b[at + j] != b[at + j + 1]
    )
    assert int(_changes(a, b, at)) == expected
    assert int(_changes(a[at:], b[at:], 0)) == expected  # a slice: its own first word


def test_word_changes_of_read_only_words() -> None:
    words = np.frombuffer(np.arange(CHANGE_SPAN + 1, dtype=np.uint16).tobytes(), np.uint16)
    assert not words.flags.writeable
    assert int(_changes(words, words, 0)) == 2**64 - 1
