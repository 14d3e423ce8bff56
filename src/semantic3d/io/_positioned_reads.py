"""Positioned reads from compiled code: ``pread`` called by numba kernels.

A kernel that reads a file itself, each of its threads its own blocks into a buffer that
stays in cache, parses a large file without returning to the interpreter between blocks
(where many threads would queue for its lock) and without a block-sized copy leaving the
cache. Used by the ``.labels`` reader and the evaluation's pair counter; callers check
``os.pread`` first (the function is linked when a kernel is first compiled, so never on a
platform that lacks it).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import numba as nb
import numpy as np
from numba import types
from numba.core.typing import signature
from numpy.typing import NDArray

_pread = cast(
    "Callable[[int, int, int, int], int]",  # what the compiled code calls it as
    types.ExternalFunction(
        "pread", signature(types.intp, types.intc, types.uintp, types.uintp, types.int64)
    ),
)
"""POSIX ``pread(fd, buffer, count, offset)``, the buffer passed as its address (an integer,
in the register a pointer takes)."""


@nb.njit(cache=True, nogil=True)
def read_fully(fd: int, buffer: NDArray[np.uint8], n_bytes: int, offset: int) -> bool:
    """Fill ``buffer[:n_bytes]`` from ``fd`` at ``offset``; False on an error or the end."""
    if n_bytes > buffer.size:
        return False
    done = 0
    while done < n_bytes:
        got = _pread(fd, buffer.ctypes.data + done, n_bytes - done, offset + done)
        if got <= 0:
            return False
        done += got
    return True
