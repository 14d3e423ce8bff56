"""What the machine itself gives on N threads: the ceilings a path's scaling is read against.

- :func:`spin`: arithmetic in registers, the same amount on every thread, no memory
  traffic. Its rate on N threads over its rate on one is the most any compute-bound path
  can gain from N threads here: below N where cores slow down when more of them run
  (turbo frequencies, shared cores of a virtual machine, another tenant).
- :func:`triad`: ``a = b + s * c`` over arrays far larger than the caches, each thread a
  contiguous slice: the memory bandwidth N threads reach (bytes read and written, counting
  the written array once).

Both are compiled with numba's threads, as the paths are, so they share the paths'
threading layer and thread cap.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

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
        for i in range(run * per, min(n, (run + 1) * per)):
            a[i] = b[i] + 0.5 * c[i]
