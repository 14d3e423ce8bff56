"""The compiled kernels' shared counter: every piece handed out once, however many threads
take them, and a thread that comes free takes the next piece."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from semantic3d.core.atomic import row_workers, take_next, take_row_block


@numba.njit(parallel=True, cache=False)
def _take_all(n_pieces: int, n_workers: int, cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    taker = np.full(n_pieces, -1, np.int64)
    times_taken = np.zeros(n_pieces, np.int64)
    taken = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):
        while True:
            piece = take_next(taken)
            if piece >= n_pieces:
                break
            total = 0.0
            for j in range(cost[piece]):  # work of unequal size
                total += np.sqrt(j + 1.0)
            taker[piece] = worker if total >= 0.0 else -2
            times_taken[piece] += 1
    return taker, times_taken


@pytest.mark.parametrize("n_workers", [1, 2, 7])
def test_every_piece_is_taken_exactly_once(n_workers: int) -> None:
    n_pieces = 5_000
    cost = np.where(np.arange(n_pieces) < 100, 20_000, 10).astype(np.int64)
    threads = min(n_workers, numba.config.NUMBA_NUM_THREADS)
    numba.set_num_threads(threads)
    try:
        taker, times_taken = _take_all(n_pieces, n_workers, cost)
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    assert (times_taken == 1).all()
    assert taker.min() >= 0 and taker.max() < n_workers


def test_the_counter_counts_from_its_value_and_leaves_the_rest() -> None:
    @numba.njit(cache=False)
    def take_three(counter: np.ndarray) -> tuple[int, int, int]:
        return take_next(counter), take_next(counter), take_next(counter)

    counter = np.array([40, 7], np.int64)
    assert take_three(counter) == (40, 41, 42)
    assert counter.tolist() == [43, 7]


def test_only_an_int64_array_is_a_counter() -> None:
    @numba.njit(cache=False)
    def take(counter: np.ndarray) -> int:
        return take_next(counter)

    with pytest.raises(numba.core.errors.TypingError):
        take(np.zeros(1, np.int32))


@numba.njit(parallel=True, cache=False)
def _rows_by_block(n_rows: int, block: int, n_threads: int) -> np.ndarray:
    times_written = np.zeros(n_rows, np.int64)
    taken = np.zeros(1, np.int64)
    for _ in numba.prange(row_workers(n_threads, n_rows, block)):
        while True:
            start, stop = take_row_block(taken, n_rows, block)
            if start >= stop:
                break
            for row in range(start, stop):
                times_written[row] += 1
    return times_written


@pytest.mark.parametrize(("n_rows", "block"), [(0, 4), (1, 4), (9, 4), (12, 4), (1000, 7)])
def test_row_blocks_cover_every_row_once(n_rows: int, block: int) -> None:
    assert (_rows_by_block(n_rows, block, 3) == 1).all()

    @numba.njit(cache=False)
    def workers(n_threads: int) -> int:
        return row_workers(n_threads, n_rows, block)

    assert workers(3) == max(1, min(3, -(-n_rows // block)))
