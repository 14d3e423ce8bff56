"""CPU seconds, wall seconds and peak traced memory of a block of test code.

The tests that bound what a refusal costs compare it with the work it refuses, both
measured in this process. Process CPU counts whatever else the process does meanwhile,
and a worker that has run hundreds of tests holds a million objects: a full collection
of the cyclic garbage collector then takes 1-2 s of CPU, wherever an allocation happens
to trigger it. So the collector is paused during a measured block; the block's own
garbage is freed by reference counting as usual, its cycles once the block ends.
"""

from __future__ import annotations

import gc
import time
import tracemalloc


class Budget:
    """CPU seconds, wall seconds and (``traced``) peak traced MB of a ``with`` block.

    Tracing allocations slows Python's allocations several times: the references a
    refusal is compared with (building an index, reading a member) are timed untraced.
    """

    def __init__(self, *, traced: bool = True) -> None:
        self.traced = traced
        self.peak_mb = float("nan")
        self.cpu_s = float("nan")
        self.wall_s = float("nan")

    def __enter__(self) -> Budget:
        self._collecting = gc.isenabled()
        gc.disable()
        if self.traced:
            tracemalloc.start()
        self._cpu = time.process_time()
        self._wall = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        self.cpu_s = time.process_time() - self._cpu
        self.wall_s = time.perf_counter() - self._wall
        if self.traced:
            self.peak_mb = tracemalloc.get_traced_memory()[1] / 1e6
            tracemalloc.stop()
        if self._collecting:
            gc.enable()

    def __str__(self) -> str:
        return f"{self.cpu_s:.3f} s CPU, {self.wall_s:.3f} s, {self.peak_mb:.1f} MB traced"
