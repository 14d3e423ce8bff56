"""The C allocator's policy for long compute jobs: freed memory kept for reuse.

glibc's ``malloc`` maps a block above its (adaptive) threshold fresh from the kernel and
returns freed memory above 128 KiB at the top of a heap. A job that allocates the same
large arrays tile after tile (a tile's feature table, its k-d tree, its sort buffers,
numba's arrays) then pays one page fault per 4 KiB of every array, every time: on the
densest tile of a 10 M-point scan about 130 k faults and 1.3 s of system time in a task of
12 s. :func:`keep_freed_memory` keeps blocks up to 32 MiB in the heap and freed memory in
the process (up to 1 GiB above the heap's top) for the next tile: 30 k faults and about
5 % less wall time on two threads, for a higher peak. Nothing else changes: results are
the same bytes.

Each heap (an *arena*) keeps its own freed memory, and glibc gives threads up to eight
arenas a core, so one a thread in practice: with a tile map's threads and each one's
OpenMP team, memory one thread freed was faulted in fresh by the next, and the peak grew
with the thread count. The policy also caps the arenas at :func:`arena_limit` (one for
every eight cores, at least two): the threads share the freed memory. They rarely
contend for it: blocks under a kilobyte come from glibc's per-thread cache without a
lock, and the prediction of a 3 M-point scan asks for about 100 k larger ones in all.
A ``MALLOC_ARENA_MAX`` or ``glibc.malloc.arena_max`` the user set is kept.

Applied by the command line's compute commands (``--threads``), not by the library on
import: a program that embeds the library keeps its own allocator policy unless it asks.
Only glibc has these settings; elsewhere nothing is changed.
"""

from __future__ import annotations

import ctypes
import os
import platform
import threading

from semantic3d.core.threads import available_cores

__all__ = ["arena_limit", "keep_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8

MMAP_THRESHOLD_BYTES = 32 << 20
"""Blocks up to this size come from the heap (glibc's largest threshold on 64 bits)."""
TRIM_THRESHOLD_BYTES = 1 << 30
"""Free memory at a heap's top kept up to this size before it goes back to the kernel."""
TOP_PAD_BYTES = 64 << 20
"""Extra asked of the kernel each time a heap grows (pages are touched only when used)."""

MIN_ARENAS = 2
"""The fewest arenas the policy leaves (one for every 8 cores, at least these)."""


def arena_limit(cores: int) -> int:
    """The arenas ``malloc`` may make on a machine of ``cores`` cores under the policy."""
    return max(MIN_ARENAS, cores // 8)


_lock = threading.Lock()
_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Set glibc's ``malloc`` to keep blocks up to :data:`MMAP_THRESHOLD_BYTES` in its
    heaps and freed memory for reuse, in at most :func:`arena_limit` heaps (once a
    process, best before it starts threads; later calls only answer). Returns whether the
    policy is in force (False where the C library is not glibc)."""
    global _applied
    with _lock:
        if _applied is None:
            _applied = _apply()
        return _applied


def _apply() -> bool:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    settings = [
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
        (_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
        (_M_TOP_PAD, TOP_PAD_BYTES),
    ]
    if not _arenas_chosen_by_user():
        settings.append((_M_ARENA_MAX, arena_limit(available_cores())))
    return all(mallopt(parameter, value) == 1 for parameter, value in settings)


def _arenas_chosen_by_user() -> bool:
    return "MALLOC_ARENA_MAX" in os.environ or "glibc.malloc.arena_max" in os.environ.get(
        "GLIBC_TUNABLES", ""
    )
