"""A connection to a Dask cluster and an ordered ``map`` over it.

:func:`connect` opens a :class:`DaskCluster` from a :class:`ClusterSpec`: a running
scheduler (``tcp://HOST:8786``) or a ``LocalCluster`` of worker *processes* started for
the job and stopped with it. :meth:`DaskCluster.map` sends a picklable function and its
items (tile jobs, file paths: never arrays) to the workers and yields the results in
input order, so anything merged from them is merged in one order whatever finished
first; progress is reported as tasks complete. Dask retries the tasks of a worker that
dies on the workers left.

Every task first limits the worker's numba, BLAS / OpenMP and torch threads to the
worker's own thread count (:func:`limit_threads`): two single-threaded workers on a
two-core machine then use two cores, not four times two.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING, Any, TypeVar

from semantic3d.core.errors import ConfigError, Semantic3DError, require

if TYPE_CHECKING:
    from distributed import Client

__all__ = [
    "ClusterError",
    "ClusterSpec",
    "DaskCluster",
    "MapProgress",
    "connect",
    "limit_threads",
    "relax_allocator",
]

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")

MapProgress = Callable[[int, int], None]
"""``progress(tasks_done, tasks_total)``."""

THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMBA_NUM_THREADS",
)
"""Environment variables set in the worker processes a :class:`DaskCluster` starts."""


class ClusterError(Semantic3DError, RuntimeError):
    """The cluster cannot be reached or a task failed on every try."""


@dataclass(frozen=True, slots=True)
class ClusterSpec:
    """Where jobs run: a running scheduler, or local worker processes started for the job.

    Attributes:
        scheduler: address of a running scheduler (``tcp://HOST:8786``).
        n_workers: worker processes to start on this machine (a ``LocalCluster``).
        threads_per_worker: threads of each started worker (and of numba / BLAS in it).
        memory_limit: memory limit of each started worker (bytes or ``"2GiB"``;
            ``"auto"`` shares the machine's memory).
        timeout_s: how long to wait for the scheduler.

    Raises:
        ConfigError: neither or both of ``scheduler`` and ``n_workers``, or a count < 1.
    """

    scheduler: str | None = None
    n_workers: int | None = None
    threads_per_worker: int = 1
    memory_limit: str | int = "auto"
    timeout_s: float = 30.0

    def __post_init__(self) -> None:
        if (self.scheduler is None) == (self.n_workers is None):
            raise ConfigError(
                "cluster: expected a scheduler address or a number of workers, found "
                + ("both" if self.scheduler is not None else "neither")
            )
        if self.n_workers is not None and self.n_workers < 1:
            raise ConfigError(f"workers: expected at least 1, found {self.n_workers}")
        if self.threads_per_worker < 1:
            raise ConfigError(
                f"threads_per_worker: expected at least 1, found {self.threads_per_worker}"
            )
        if self.scheduler is not None and "://" not in self.scheduler:
            raise ConfigError(
                f"scheduler: expected an address like tcp://HOST:8786, found {self.scheduler!r}"
            )


class DaskCluster:
    """A client of a Dask cluster (use as a context manager; see :func:`connect`).

    Attributes:
        client: the ``distributed.Client``.
        dashboard_link: address of the scheduler's dashboard (None when it has none).
    """

    def __init__(self, spec: ClusterSpec) -> None:
        require("distributed", "dask")
        from distributed import Client, LocalCluster

        self.spec = spec
        self._local: LocalCluster | None = None
        # Dask's own log lines (every worker started, every connection closed, the
        # CommClosedError of a worker that outlives the scheduler by a heartbeat at
        # shutdown) are shown with --verbose only; failed tasks are raised here anyway.
        self._quiet = logging.getLogger().getEffectiveLevel() > logging.INFO
        self._log_levels = _quiet_dask_logs(logging.WARNING) if self._quiet else None
        try:
            if spec.scheduler is not None:
                self.client: Client = Client(spec.scheduler, timeout=spec.timeout_s)
            else:
                import dask

                # set in each worker once it runs (never in this process)
                env = {name: str(spec.threads_per_worker) for name in THREAD_VARIABLES}
                spawn = _spawn_environment(quiet=self._quiet)
                saved = {name: os.environ.get(name) for name in [*spawn, "PYTHONHASHSEED"]}
                try:
                    with dask.config.set({"distributed.nanny.pre-spawn-environ": spawn}):
                        self._local = LocalCluster(
                            n_workers=spec.n_workers,
                            threads_per_worker=spec.threads_per_worker,
                            processes=True,
                            memory_limit=spec.memory_limit,
                            host="127.0.0.1",
                            dashboard_address=":0",
                            env=env,
                        )
                finally:
                    _restore_variables(saved)
                self.client = Client(self._local, timeout=spec.timeout_s)
        except OSError as exc:  # TimeoutError included
            self.close()
            where = spec.scheduler or "a local cluster"
            raise ClusterError(f"{where}: expected a Dask scheduler, found none ({exc})") from exc
        link = self.client.dashboard_link
        self.dashboard_link: str | None = link or None
        logger.info("connected to %s (dashboard %s)", self.client.scheduler.address, link)

    def __enter__(self) -> DaskCluster:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Disconnect; stop the workers this object started (quietly: a clean shutdown
        prints nothing)."""
        if self._quiet:
            _quiet_dask_logs(logging.CRITICAL)
        try:
            client = getattr(self, "client", None)
            if client is not None:
                client.close()
            if self._local is not None:
                self._local.close()
                self._local = None
        finally:
            if self._log_levels is not None:
                _restore_log_levels(self._log_levels)
                self._log_levels = None

    @property
    def n_threads(self) -> int:
        """Threads of all workers together (0 while none is connected)."""
        return sum(self.client.nthreads().values())

    def worker_memory(self) -> dict[str, tuple[int, int]]:
        """``{worker address: (resident bytes now, peak resident bytes)}`` of every worker."""
        memory: dict[str, tuple[int, int]] = self.client.run(process_memory)
        return memory

    def map_unordered(
        self,
        function: Callable[[T], R],
        items: Sequence[T],
        *,
        progress: MapProgress | None = None,
    ) -> Iterator[tuple[int, R]]:
        """``(index, function(items[index]))`` as tasks finish (for merges that need no order).

        Raises:
            ClusterError: a task failed on every try (e.g. its workers kept dying).
        """
        from distributed import as_completed

        total = len(items)
        if progress is not None:
            progress(0, total)
        if not total:
            return
        futures = self.client.map(
            _run_task, [function] * total, items, pure=False, key=_task_keys(function, total)
        )
        index = {future.key: number for number, future in enumerate(futures)}
        try:
            # Dask's as_completed runs on the loop of the newest client unless told; with
            # two clients in one process (two clusters open) it then waited on this
            # client's futures from the other's loop and could miss their completion for ever.
            completed = as_completed(
                futures, loop=self.client.loop, with_results=True, raise_errors=False
            )
            for done, (future, result) in enumerate(completed, start=1):
                if future.status == "error":
                    error = future.exception()
                    if isinstance(error, Semantic3DError):
                        raise error
                    raise ClusterError(
                        f"task {index[future.key]} ({items[index[future.key]]!r}): {error!r}"
                    ) from error
                number = index[future.key]
                future.release()
                if progress is not None:
                    progress(done, total)
                yield number, result
        finally:
            self.client.cancel(futures)

    def map(
        self,
        function: Callable[[T], R],
        items: Sequence[T],
        *,
        progress: MapProgress | None = None,
    ) -> Iterator[R]:
        """``function(item)`` for every item, run on the workers, yielded in input order.

        ``function`` and the items must pickle (a module-level function, maybe in a
        ``functools.partial``; paths and tile jobs, not arrays). Results that finish
        early wait on this side until those before them arrive.

        Raises:
            ClusterError: a task failed on every try.
        """
        waiting: dict[int, R] = {}
        next_index = 0
        for number, result in self.map_unordered(function, items, progress=progress):
            waiting[number] = result
            while next_index in waiting:
                yield waiting.pop(next_index)
                next_index += 1


_DASK_LOGGERS = ("distributed", "tornado", "asyncio", "bokeh")


def _spawn_environment(*, quiet: bool) -> dict[str, str | None]:
    """Dask's ``distributed.nanny.pre-spawn-environ`` for the workers started here.

    The nanny runs in this process and writes these variables into this process's own
    environment before it starts each worker. Dask's defaults there include
    ``OMP_NUM_THREADS=1``: left alone, it capped this process's thread budget at one (the
    client then read and cut the scan into tiles on one thread). The thread variables are
    therefore dropped here (None) and set in each worker after its start instead (the
    cluster's ``env``); a quiet run adds Dask's log level, which a worker reads only as
    it starts.
    """
    import dask

    spawn: dict[str, str | None] = dict(
        dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {}
    )
    for name in THREAD_VARIABLES:
        spawn[name] = None
    if quiet:  # the workers' own log lines (a heartbeat lost at shutdown) stay out
        spawn["DASK_LOGGING__DISTRIBUTED"] = "critical"
    return spawn


def _restore_variables(saved: dict[str, str | None]) -> None:
    """Put this process's environment variables back as they were (None: absent)."""
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


def _quiet_dask_logs(level: int) -> dict[str, int]:
    """Raise Dask's loggers (and those of its event loop) to ``level``; return the old levels."""
    before = {}
    for name in _DASK_LOGGERS:
        log = logging.getLogger(name)
        before[name] = log.level
        log.setLevel(max(level, log.level))
    return before


def _restore_log_levels(levels: dict[str, int]) -> None:
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)


def _task_keys(function: Callable[..., Any], total: int) -> list[str]:
    import uuid

    name = getattr(function, "__name__", None) or getattr(
        getattr(function, "func", None), "__name__", "task"
    )
    run = uuid.uuid4().hex[:12]
    return [f"semantic3d-{name}-{run}-{number}" for number in range(total)]


def _run_task(function: Callable[[T], R], item: T) -> R:
    """What a worker runs: limit the threads (and tune the allocator), then the task."""
    limit_threads()
    if "allocator" not in _LIMITED:
        _LIMITED["allocator"] = int(relax_allocator())
    return function(item)


_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
"""``mallopt`` parameter numbers (glibc's ``malloc.h``)."""


def relax_allocator(mmap_threshold: int = 32 << 20, trim_threshold: int = 64 << 20) -> bool:
    """Give glibc's allocator back the thresholds it settles at by itself; True if done.

    Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_`` set (64 KiB), and per
    ``mallopt(3)`` setting it turns off glibc's dynamic mmap threshold: every array over
    128 KiB is then a fresh ``mmap``, its pages faulted in and zeroed on each allocation.
    The per-tile kernels allocate many such arrays (the graph cut's most of all), and a
    tile took 1.7-1.9x the time it takes in an ordinary process. These values are the
    ones glibc's dynamic rule reaches on 64-bit Linux (32 MiB, and twice that for the
    trim): freed memory up to 64 MiB per worker stays for reuse. No library exposes
    ``mallopt``, hence ``ctypes``; elsewhere (not glibc, or the variable unset) nothing
    is changed.
    """
    if not sys.platform.startswith("linux") or "MALLOC_TRIM_THRESHOLD_" not in os.environ:
        return False
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(
        mallopt(_M_TRIM_THRESHOLD, trim_threshold)
    )


_LIMITED: dict[str, int] = {}


def limit_threads(n_threads: int | None = None) -> int:
    """Limit numba, BLAS / OpenMP and torch threads of this process; return the limit.

    ``n_threads`` defaults to the Dask worker's thread count (1 outside a worker). numba's
    setting belongs to the calling thread, so it is set on every call; the others are
    process-wide and set once.
    """
    if n_threads is None:
        try:
            from distributed import get_worker

            n_threads = int(get_worker().state.nthreads)
        except (ImportError, ValueError):
            n_threads = 1

    numba = sys.modules.get("numba")
    if numba is not None:
        numba.set_num_threads(min(n_threads, int(numba.config.NUMBA_NUM_THREADS)))
    if _LIMITED.get("threads") != n_threads:
        for name in THREAD_VARIABLES[:3]:
            os.environ[name] = str(n_threads)
        from threadpoolctl import threadpool_limits

        threadpool_limits(n_threads)
        torch = sys.modules.get("torch")
        if torch is not None:
            torch.set_num_threads(n_threads)
        _LIMITED["threads"] = n_threads
    return n_threads


def process_memory() -> tuple[int, int]:
    """This process's resident and peak resident memory, in bytes (Linux, macOS)."""
    import resource

    import psutil

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return psutil.Process().memory_info().rss, peak if sys.platform == "darwin" else peak << 10


def connect(spec: ClusterSpec) -> DaskCluster:
    """Open the cluster ``spec`` describes (use the result as a context manager).

    Raises:
        MissingExtraError: Dask is not installed (extra ``dask``).
        ClusterError: the scheduler does not answer.
    """
    return DaskCluster(spec)


def map_items(
    cluster: DaskCluster | None,
    function: Callable[[T], R],
    items: Iterable[T],
    *,
    progress: MapProgress | None = None,
) -> Iterator[R]:
    """``function`` over ``items`` on ``cluster``, or in this process when it is None."""
    sequence = list(items)
    if cluster is not None:
        yield from cluster.map(function, sequence, progress=progress)
        return
    for done, item in enumerate(sequence, start=1):
        yield function(item)
        if progress is not None:
            progress(done, len(sequence))
