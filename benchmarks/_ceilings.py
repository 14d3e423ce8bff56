"""What the machine itself gives on N threads: the ceilings a path's scaling is read against.

- :func:`spin`: arithmetic in registers, the same amount on every thread, no memory
  traffic. Its rate on N threads over its rate on one is the most any compute-bound path
  can gain from N threads here: below N where cores slow down when more of them run
  (turbo frequencies, shared cores of a virtual machine, another tenant).
- :func:`triad`: ``a = b + s * c`` over arrays far larger than the caches, each thread a
  contiguous slice: the memory bandwidth N threads reach (bytes read and written, counting
  the written array once).
- :func:`read_file` and :func:`fill`: a file's bytes read from compiled code, each thread a
  run of cache-sized blocks into its own buffer, and a result written once into fresh
  memory: the floor of a path that reads a file and hands back what it found.

Both are compiled with numba's threads, as the paths are, so they share the paths'
threading layer and thread cap.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from semantic3d.io._positioned_reads import read_fully

CHAINS = 8
"""Independent multiply-add chains a thread runs side by side: enough to keep the
floating-point units busy rather than wait on one chain's latency."""


@nb.njit(parallel=True, nogil=True)
def spin(n_threads: int, steps: int) -> float:  # pragma: no cover - compiled
    """``steps`` rounds of :data:`CHAINS` multiply-adds on each of ``n_threads`` threads;
    a value that depends on all of them (so none is optimised away)."""
    sums = np.zeros(n_threads)
    for run in nb.prange(n_threads):
        x = np.empty(CHAINS)
        for k in range(CHAINS):
            x[k] = 1.0 + 1e-3 * k + 1e-6 * run
        a0, a1, a2, a3, a4, a5, a6, a7 = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]
        for _ in range(steps):
            a0 = a0 * 0.999999 + 1e-7
            a1 = a1 * 0.999999 + 1e-7
            a2 = a2 * 0.999999 + 1e-7
            a3 = a3 * 0.999999 + 1e-7
            a4 = a4 * 0.999999 + 1e-7
            a5 = a5 * 0.999999 + 1e-7
            a6 = a6 * 0.999999 + 1e-7
            a7 = a7 * 0.999999 + 1e-7
        sums[run] = a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7
    return float(sums.sum())


@nb.njit(parallel=True, nogil=True)
def triad(
    a: NDArray[np.float64], b: NDArray[np.float64], c: NDArray[np.float64], n_threads: int
) -> None:  # pragma: no cover - compiled
    """``a = b + 0.5 c``, each of ``n_threads`` threads one contiguous slice."""
    n = a.shape[0]
    per = (n + n_threads - 1) // n_threads
    for run in nb.prange(n_threads):
        low, high = run * per, min(n, (run + 1) * per)
        out, left, right = a[low:high], b[low:high], c[low:high]
        for i in range(out.shape[0]):  # slices indexed from 0: LLVM vectorises the loop
            out[i] = left[i] + 0.5 * right[i]


@nb.njit(parallel=True, nogil=True)
def fill(a: NDArray[np.uint8], n_threads: int) -> None:  # pragma: no cover - compiled
    """Write every byte of ``a`` once, each of ``n_threads`` threads one contiguous slice
    (fresh pages: first touched by the thread that writes them)."""
    n = a.shape[0]
    per = (n + n_threads - 1) // n_threads
    for run in nb.prange(n_threads):
        part = a[run * per : min(n, (run + 1) * per)]
        for i in range(part.shape[0]):  # from 0, vectorised (from ``run * per``: 2.5x slower)
            part[i] = 1


@nb.njit(parallel=True, nogil=True)
def read_file(fd: int, size: int, block: int, n_threads: int) -> int:  # pragma: no cover
    """Read the first ``size`` bytes of ``fd`` in ``block``-byte positioned reads, each of
    ``n_threads`` threads a contiguous run of blocks into a buffer of its own (which stays
    in cache, as the readers' do); the bytes read."""
    n_blocks = (size + block - 1) // block
    per = (n_blocks + n_threads - 1) // n_threads
    got = np.zeros(n_threads, np.int64)
    for run in nb.prange(n_threads):
        buffer = np.empty(block, np.uint8)
        for b in range(run * per, min(n_blocks, (run + 1) * per)):
            count = min(block, size - b * block)
            if read_fully(fd, buffer, count, b * block):
                got[run] += count
    return int(got.sum())
