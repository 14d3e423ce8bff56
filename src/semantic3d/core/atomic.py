"""An atomic counter for compiled kernels: work handed out as threads come free.

numba's parallel loops divide their iterations into one equal block per thread before
they start (its OpenMP layer offers no dynamic schedule, and ``set_parallel_chunksize``
did not balance a loop whose first half cost ten times its second). A kernel whose pieces
cost unequal time (parsing on a loaded machine, neighbour searches where the points are
dense) then waits for its slowest block with the other threads idle. numba has no atomic
operation on the CPU, so :func:`take_next` is one LLVM ``atomicrmw add``: each of the
kernel's threads takes the next piece's number until none is left::

    taken = np.zeros(1, np.int64)
    for _ in nb.prange(n_workers):
        while True:
            piece = take_next(taken)
            if piece >= n_pieces:
                break
            ...  # piece writes only its own outputs

Results do not depend on which thread ran which piece. Kernels over rows take them in
blocks (:func:`row_workers`, :func:`take_row_block`)::

    taken = np.zeros(1, np.int64)
    for _ in nb.prange(row_workers(n_threads, n_rows, BLOCK)):
        while True:
            start, stop = take_row_block(taken, n_rows, BLOCK)
            if start >= stop:
                break
            for row in range(start, stop):
                ...
"""

from __future__ import annotations

from typing import Any

from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["row_workers", "take_next", "take_row_block"]


def _take_next(typingctx: Any, counter: Any) -> Any:  # pragma: no cover - compiled
    """``counter[0] += 1`` atomically; returns the value before (``counter``: int64 array)."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64):
        return None
    signature = types.int64(counter)

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        array_type = sig.args[0]
        array = context.make_array(array_type)(context, builder, args[0])
        zero = context.get_constant(types.intp, 0)
        pointer = cgutils.get_item_pointer(context, builder, array_type, array, [zero])
        one = context.get_constant(types.int64, 1)
        return builder.atomic_rmw("add", pointer, one, "monotonic")

    return signature, codegen


take_next: Any = intrinsic(_take_next)
"""``take_next(counter)`` in a compiled kernel: ``counter[0] += 1`` as one atomic step,
returning the value before (``counter``: a C-contiguous int64 array)."""


@njit(cache=True, nogil=True, inline="always")
def take_row_block(counter: Any, n_rows: Any, block: Any) -> tuple[Any, Any]:  # pragma: no cover
    """The next block of rows ``0 .. n_rows`` in blocks of ``block`` (:func:`take_next`):
    ``(start, stop)``, with ``start >= stop`` once every block has been taken."""
    start = take_next(counter) * block
    return start, min(n_rows, start + block)


@njit(cache=True, nogil=True, inline="always")
def row_workers(n_threads: Any, n_rows: Any, block: Any) -> Any:  # pragma: no cover
    """How many threads to start on ``n_rows`` rows in blocks of ``block``: no more than
    there are blocks, at least one."""
    return max(1, min(n_threads, (n_rows + block - 1) // block))
