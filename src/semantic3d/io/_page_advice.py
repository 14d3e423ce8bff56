"""Page advice from compiled code: ``madvise`` called by numba kernels.

The ASCII point reader maps a scan and drops the pages behind its cursor from the mapping
(so that the process's resident memory does not grow with the file). Dropping is work for
the kernel in proportion to the pages (4-6 ms for every 135 MB on the 2-core machine), and
from the interpreter it ran between two windows with every other thread idle; called
here, one of the parser's own threads does it while the others parse.

Where the C library has no ``madvise`` (Windows, where the reader passes nothing to
drop), the symbol is bound to a function that does nothing, only so that the kernels
that name it compile.
"""

from __future__ import annotations

import ctypes
import mmap
from collections.abc import Callable
from typing import cast

from llvmlite import binding
from numba import types
from numba.core.typing import signature

DROP_ADVICE: int = getattr(mmap, "MADV_DONTNEED", 0)
"""The advice that drops pages from a mapping (0 where there is none: nothing is dropped)."""

_SIGNATURE = signature(types.intc, types.uintp, types.uintp, types.intc)

if not DROP_ADVICE:  # pragma: no cover - platforms without madvise

    def _nothing(address: int, length: int, advice: int) -> int:
        return 0

    _AS_C = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
    _NOTHING = _AS_C(_nothing)  # kept alive with the module
    binding.add_symbol("madvise", ctypes.cast(_NOTHING, ctypes.c_void_p).value)

advise = cast(
    "Callable[[int, int, int], int]",  # what the compiled code calls it as
    types.ExternalFunction("madvise", _SIGNATURE),
)
"""POSIX ``madvise(address, length, advice)``, the address as an integer (in the register
a pointer takes)."""
