"""How many threads the package computes with: every core by default, fewer when asked.

One number, the *thread budget* (:func:`thread_budget`), sizes everything that runs in
parallel: numba's parallel kernels, the package's thread pools (segments of a text file,
tiles of a scan, scans of a submission), scikit-learn's forest and the BLAS / OpenMP pools
of compiled libraries. It is, first found:

1. the limit set by :func:`set_thread_limit` (the command line's ``--threads N``);
2. the smallest positive ``NUMBA_NUM_THREADS`` or ``OMP_NUM_THREADS`` of the environment;
3. the cores this process may run on (its CPU affinity).

Results never depend on it: every parallel path of the package splits work into pieces
whose results are combined in a fixed order, so any budget gives the same bytes (tested).

numba keeps its thread count per calling thread, so a thread pool of the package sets it
in each worker (:func:`map_in_threads`); :func:`numba_threads` does it for one block of
work. Nothing here imports numba: it is configured only when something else loaded it.
"""

from __future__ import annotations

import importlib
import os
import queue
import sys
import threading
from collections import deque
from collections.abc import Callable, Generator, Hashable, Iterable, Iterator, Mapping
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from contextlib import contextmanager, suppress
from typing import TypeVar

from semantic3d.core.timeline import inside, open_span

__all__ = [
    "ENVIRONMENT_VARIABLES",
    "apportion_threads",
    "available_cores",
    "concurrent_kernels_supported",
    "current_thread_limit",
    "enclosing_map_threads",
    "iter_ahead",
    "map_in_threads",
    "numba_threads",
    "serial_section",
    "set_thread_limit",
    "take_free_threads",
    "thread_budget",
    "thread_limit",
]

T = TypeVar("T")
R = TypeVar("R")
K = TypeVar("K", bound=Hashable)

ENVIRONMENT_VARIABLES = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS")
"""Variables that cap the budget when no limit was set (the smallest positive one wins)."""

_POOL_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""Set for libraries not loaded yet when a limit is set (numba's is set apart)."""

_limit: int | None = None
_task = threading.local()  # a task's share of the budget (see _task_budget)
_saved_environment: dict[str, str | None] = {}


def available_cores() -> int:
    """Cores this process may run on (its affinity mask where the system has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def _environment_limit() -> int | None:
    values = []
    for name in ENVIRONMENT_VARIABLES:
        text = os.environ.get(name, "").strip()
        if text.isdigit() and int(text) > 0:
            values.append(int(text))
    return min(values) if values else None


def thread_budget() -> int:
    """Threads the package's parallel work may use now (see the module docs); inside a
    task of :func:`map_in_threads` (or a :func:`numba_threads` block), the task's share."""
    share: int | None = getattr(_task, "budget", None)
    if share is not None:
        return share
    if _limit is not None:
        return _limit
    found = _environment_limit()
    return found if found is not None else available_cores()


def current_thread_limit() -> int | None:
    """The limit :func:`set_thread_limit` set (None: none)."""
    return _limit


def set_thread_limit(n_threads: int | None) -> int:
    """Cap this process's compute threads at ``n_threads`` (None: the default again).

    Applies at once where it can: numba in the calling thread, the BLAS / OpenMP pools of
    loaded libraries (through threadpoolctl when installed), and the environment of
    libraries loaded later (``NUMBA_NUM_THREADS`` only while numba is not loaded, so that
    its pool is sized for the limit; numba then keeps that pool, and the variable, for the
    life of the process). Returns the budget now in force.

    Raises:
        ValueError: ``n_threads`` is below 1.
    """
    global _limit
    if n_threads is not None and (isinstance(n_threads, bool) or int(n_threads) < 1):
        raise ValueError(f"threads: expected at least 1, found {n_threads!r}")
    _limit = None if n_threads is None else int(n_threads)
    if _limit is None:
        _restore_environment()
    else:
        names = [*_POOL_VARIABLES, *(() if "numba" in sys.modules else ("NUMBA_NUM_THREADS",))]
        for name in names:
            _saved_environment.setdefault(name, os.environ.get(name))
            os.environ[name] = str(_limit)
    budget = thread_budget()
    _set_numba_threads(budget)
    if "threadpoolctl" in sys.modules or _limit is not None:
        _limit_native_pools(budget)
    return budget


def _restore_environment() -> None:
    for name, value in _saved_environment.items():
        if name == "NUMBA_NUM_THREADS" and "numba" in sys.modules:
            # numba sized its pool from it and rereads it on every compilation: another
            # value now would stop it compiling; its pool cannot grow anyway
            continue
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    _saved_environment.clear()


def _set_numba_threads_here(n_threads: int) -> None:
    numba = sys.modules.get("numba")
    if numba is not None and hasattr(numba, "set_num_threads"):
        numba.set_num_threads(max(1, min(n_threads, int(numba.config.NUMBA_NUM_THREADS))))


def _set_numba_threads(n_threads: int) -> None:
    numba = sys.modules.get("numba")
    if numba is None or not hasattr(numba, "set_num_threads"):
        return
    numba.set_num_threads(max(1, min(n_threads, int(numba.config.NUMBA_NUM_THREADS))))


def _limit_native_pools(n_threads: int) -> None:
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n_threads)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: environment variables cover libraries loaded later
        return
    threadpool_limits(n_threads)


@contextmanager
def numba_threads(n_threads: int | None = None) -> Iterator[int]:
    """Run a block with numba's kernels on ``n_threads`` (default the budget) in this thread.

    numba keeps the count per thread; the previous one is restored on exit. Yields the
    count in force (never above the size of numba's pool).
    """
    wanted = thread_budget() if n_threads is None else max(1, int(n_threads))
    numba = sys.modules.get("numba")
    if numba is None or not hasattr(numba, "get_num_threads"):
        with _task_budget(wanted):
            yield wanted
        return
    before = numba.get_num_threads()
    count = max(1, min(wanted, int(numba.config.NUMBA_NUM_THREADS)))
    numba.set_num_threads(count)
    try:
        with _task_budget(wanted):
            yield count
    finally:
        numba.set_num_threads(before)


@contextmanager
def _task_budget(n_threads: int) -> Iterator[None]:
    """Within the block, :func:`thread_budget` in this thread is ``n_threads`` (work that
    fans out again from a task uses the task's share, not the whole budget)."""
    before = getattr(_task, "budget", None)
    _task.budget = n_threads
    try:
        yield
    finally:
        _task.budget = before


def map_in_threads(
    function: Callable[[T], R],
    items: Iterable[T],
    *,
    n_threads: int | None = None,
    ordered: bool = True,
    numba_threads_per_task: Callable[[T], int] | int = 1,
    max_pending: int | None = None,
    lend_tail: bool = True,
    name: str = "semantic3d",
) -> Generator[R, None, None]:
    """``function(item)`` for every item on a pool of ``n_threads`` (default the budget).

    Results come in input order (``ordered``) or as tasks finish. At most ``max_pending``
    tasks (default twice the threads) are submitted or waiting to be yielded at once, so
    memory is bounded by them. Each task runs with numba on ``numba_threads_per_task``
    threads (a number, or a function of the item): 1 where tasks alone fill the cores. A
    task starts only when its threads are free, so the tasks running at once never use
    more than ``n_threads`` threads together. Run inside another map's task with one
    thread a task, it lends that map the threads its tail leaves idle (unless
    ``lend_tail`` is False: many short items, whose tail is short, while the task's next
    step needs its threads back), and once that map has started all its tasks, it takes a
    share of the threads that map's ended tasks gave back while it still has items
    waiting (:class:`_TailLender`).
    The first exception raised by a task is raised here (the earliest in input order when
    ``ordered``); tasks not started are cancelled and running ones are waited for, also
    when the caller stops iterating. With one thread everything runs in the calling thread
    (same results), unless it can grow inside another map's task.
    """
    n_threads = thread_budget() if n_threads is None else max(1, int(n_threads))
    iterator = iter(items)
    if n_threads > 1 and not concurrent_kernels_supported():
        for item in iterator:  # one task at a time, each with every thread
            with numba_threads(n_threads):
                yield function(item)
        return
    if n_threads == 1 and not (numba_threads_per_task == 1 and enclosing_map_threads() > 1):
        for item in iterator:
            with numba_threads(_task_threads(numba_threads_per_task, item, 1)):
                yield function(item)
        return

    def pending_limit(threads: int) -> int:
        return max(threads, 2 * threads if max_pending is None else int(max_pending))

    limit = pending_limit(n_threads)
    tokens = _Tokens(n_threads)
    # inside an enclosing map's task: the tail's idle threads are lent to that map, and
    # the threads its ended tasks gave back are taken while items still wait
    lender = _TailLender(lend=lend_tail) if numba_threads_per_task == 1 else None
    workers = n_threads if lender is None else max(n_threads, lender.ceiling)

    parent = open_span()  # the tasks' spans go under the step that mapped them

    def run(item: T, ticket: int) -> R:
        count = _task_threads(numba_threads_per_task, item, n_threads)
        with tokens.held(count, ticket), numba_threads(count), inside(parent):
            return function(item)

    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name)
    pending: deque[Future[R]] = deque()
    try:
        exhausted = False
        while True:
            if lender is not None and n_threads < workers:
                waiting = tokens.waiting() if exhausted else workers
                grown = lender.grow(min(waiting, workers - n_threads))
                if grown:
                    tokens.give_back(grown)
                    n_threads += grown
                    limit = pending_limit(n_threads)
            while not exhausted and len(pending) < limit:
                try:
                    item = next(iterator)
                except StopIteration:
                    exhausted = True
                    tokens.draining = True  # the last tasks may take threads given back
                    break
                pending.append(pool.submit(run, item, tokens.ticket()))
            if not pending:
                return
            busy = [future for future in pending if not future.done()] if exhausted else []
            if lender is not None and exhausted:
                lender.keep(len(busy))
            if ordered:
                if busy and lender is not None and lender.lending and not pending[0].done():
                    wait(busy, return_when=FIRST_COMPLETED)  # lend as each task ends
                    continue
                yield pending.popleft().result()
                continue
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in [f for f in pending if f in done]:
                pending.remove(future)
                yield future.result()
    finally:
        for future in pending:
            future.cancel()
        tokens.close()
        pool.shutdown(wait=True)
        if lender is not None:
            lender.take_back()


_LAYER_MODULES = ("numba.np.ufunc.tbbpool", "numba.np.ufunc.omppool")


def concurrent_kernels_supported() -> bool:
    """Whether numba's parallel kernels may be launched from several threads at once: its
    ``tbb`` and ``omp`` threading layers allow it, its ``workqueue`` fallback (no TBB, no
    OpenMP runtime) aborts the process. Without it the thread maps run one task at a
    time (with every thread). True while numba is not loaded (nothing to launch)."""
    numba = sys.modules.get("numba")
    if numba is None:
        return True
    try:
        return str(numba.threading_layer()) != "workqueue"
    except ValueError:  # no parallel kernel launched yet: the layer numba will choose
        layer = str(numba.config.THREADING_LAYER)
        if layer == "workqueue":
            return False
        for module in _LAYER_MODULES:
            try:
                importlib.import_module(module)
            except ImportError:
                continue
            return True
        return False


class _Tokens:
    """``n`` threads' worth of tokens; a task holds as many as it runs threads. Tasks take
    them in the order they were submitted (a large task is not starved by small ones)."""

    def __init__(self, n: int) -> None:
        self.total = n  # the map's threads
        self.free = n
        self.turn = 0
        self.tickets = 0
        self.running = 0  # tasks holding tokens
        self.draining = False  # every item of the map handed out
        self.open = True
        self.condition = threading.Condition()

    def close(self) -> None:
        """Let waiting tasks run at once (tasks cancelled before them never take a turn)."""
        with self.condition:
            self.open = False
            self.condition.notify_all()

    def ticket(self) -> int:
        """The next task's place in line (taken when it is submitted)."""
        self.tickets += 1
        return self.tickets - 1

    @contextmanager
    def held(self, count: int, ticket: int) -> Iterator[None]:
        """Hold ``count`` tokens for the block (the task's thread may give some back for
        a while: :func:`serial_section`)."""
        with self.condition:
            self.condition.wait_for(
                lambda: not self.open or (self.turn == ticket and self.free >= count)
            )
            self.free -= count
            self.turn += 1
            self.running += 1
            self.condition.notify_all()
        _task.held = [self, count]
        try:
            yield
        finally:
            held = _task.held
            _task.held = None
            with self.condition:
                self.running -= 1
            self.give_back(held[1])

    def take_spare(self, at_most: int | None = None) -> int:
        """Once every task of the map has started: a running task's share of the free
        tokens, ``at_most`` of them (taken; 0 while tasks still wait for theirs)."""
        with self.condition:
            if not self.draining or self.turn != self.tickets or self.free <= 0:
                return 0
            taken = -(-self.free // max(1, self.running))
            if at_most is not None:
                taken = max(0, min(taken, at_most))
            self.free -= taken
            return taken

    def waiting(self) -> int:
        """Tasks submitted that have not started yet."""
        with self.condition:
            return self.tickets - self.turn

    def give_back(self, count: int) -> None:
        with self.condition:
            self.free += count
            self.condition.notify_all()

    def take_up_to(self, count: int) -> int:
        """Take at most ``count`` free tokens without waiting; return how many."""
        with self.condition:
            taken = max(0, min(count, self.free))
            self.free -= taken
            return taken


@contextmanager
def serial_section() -> Iterator[None]:
    """A block of a thread-map task that runs on one thread (a graph cut, Python steps).

    The task's other threads go back to the map for the block, so another task can use
    them, and are taken again afterwards as far as they are free (the task goes on with
    fewer kernel threads otherwise: never more threads than the map's at once). Outside a
    map's task nothing changes. Results do not depend on it.
    """
    held = getattr(_task, "held", None)
    if held is None or held[1] <= 1:
        yield
        return
    tokens, count = held
    tokens.give_back(count - 1)
    held[1] = 1
    try:
        with numba_threads(1):
            yield
    finally:
        held[1] = 1 + tokens.take_up_to(count - 1)
        _set_numba_threads_here(held[1])
        _task.budget = held[1]


def apportion_threads(work: Mapping[K, float], n_threads: int) -> dict[K, int]:
    """Threads for each task of a map of ``n_threads``, by its share of the ``work``.

    A task whose share ``n_threads * work / total`` is a thread or more is a *large* task;
    the others are *small* and get one thread each. Seats go by largest remainders
    (Hamilton's method): each large task gets the whole threads of its share, the seats
    left go to the largest fractions. The small tasks are one more party when their shares
    add up to a thread or more: they then keep the seats their work earns together, and
    start beside the large tasks instead of all at the end, where many small tasks at once
    mostly wait for each other (for the interpreter between their short kernels). With
    less than a thread's work between them, the large tasks share every seat and the
    small ones follow. Either way the large tasks never take more than ``n_threads``
    together (rounding each share up could, and the last large task would wait for
    another to end).
    """
    n = max(1, int(n_threads))
    total = float(sum(max(0.0, float(w)) for w in work.values()))
    if total <= 0.0:
        return {key: 1 for key in work}
    quota = {key: n * max(0.0, float(w)) / total for key, w in work.items()}
    large = [key for key in work if quota[key] >= 1.0]
    group = float(sum(q for q in quota.values() if q < 1.0))
    if group < 1.0:  # the small tasks follow the large ones, which share every seat
        scale = n / (n - group)
        quota.update({key: quota[key] * scale for key in large})
        group = 0.0
    seats = {key: int(quota[key]) for key in large}
    group_seats = int(group)
    # the seats left, to the largest remainders (ties: the larger task, then input order)
    remainders: list[tuple[float, float, int, K | None]] = [
        (quota[key] - seats[key], quota[key], -at, key) for at, key in enumerate(large)
    ]
    if group:
        remainders.append((group - group_seats, group, -len(large), None))
    left = max(0, n - sum(seats.values()) - group_seats)
    for _, _, _, key in sorted(remainders, key=lambda r: r[:3], reverse=True)[:left]:
        if key is not None:
            seats[key] += 1
    return {key: seats.get(key, 1) for key in work}


def enclosing_map_threads() -> int:
    """In a thread map's task, the map's threads: the most this task's nested maps of one
    thread a task can come to run on (:func:`map_in_threads`); the budget elsewhere."""
    held = getattr(_task, "held", None)
    return thread_budget() if held is None else int(held[0].total)


def take_free_threads() -> int:
    """In a thread map's task, once the map has started its last task: take a share of the
    threads that finished tasks gave back, for numba's kernels and :func:`thread_budget` in
    this task from here on (its tokens, given back when it ends). A map's last tasks then
    go on with the threads the others left, instead of each on its own share while the
    rest idle. Call it between steps of a long task. Returns this task's thread count
    (the budget outside a map's task). Results do not depend on it."""
    held = getattr(_task, "held", None)
    if held is None:
        return thread_budget()
    tokens, count = held
    taken = tokens.take_spare()
    if taken:
        held[1] = count + taken
        _set_numba_threads_here(held[1])
        _task.budget = held[1]
    return int(held[1])


class _TailLender:
    """Lends an enclosing map the threads a nested map's tail leaves idle, and grows the
    nested map with the threads the enclosing map's ended tasks gave back.

    A map run inside another map's task (a tile's graph cuts or parts, one thread each)
    holds the task's threads until its last item ends; once every item has been handed
    out, the task keeps as many as items still run or wait (at least one) and gives the
    rest back, so another task of the enclosing map can start on them. What it gave is
    taken back afterwards as far as it is free (never more threads than the enclosing
    map's at once). Once the enclosing map has started all its tasks, the nested map also
    takes a share of its free threads while it has items waiting (:meth:`grow`): a large
    task that started on a few threads goes on with those its neighbours left, instead
    of them idling until its next step. Outside a map's task it does nothing. Results do
    not depend on it.
    """

    def __init__(self, *, lend: bool = True) -> None:
        self.held = getattr(_task, "held", None)  # the calling task's [tokens, count]
        self.count = 0 if self.held is None else int(self.held[1])
        self.lend = lend

    @property
    def lending(self) -> bool:
        return self.lend and self.held is not None and self.count > 1

    @property
    def ceiling(self) -> int:
        """The most threads the nested map can come to run on: the enclosing map's."""
        return 0 if self.held is None else int(self.held[0].total)

    def grow(self, at_most: int) -> int:
        """Take up to ``at_most`` of the enclosing map's free threads for the task (a
        running task's share; none while that map's tasks still wait); return how many."""
        if self.held is None or at_most <= 0:
            return 0
        taken = int(self.held[0].take_spare(at_most))
        if taken:
            self.held[1] += taken
            self.count = max(self.count, int(self.held[1]))
            _set_numba_threads_here(self.held[1])
            _task.budget = self.held[1]
        return taken

    def keep(self, busy: int) -> None:
        """Keep ``busy`` of the task's threads (at least one), give back the others."""
        if self.held is None or not self.lend:
            return
        keep = max(1, busy)
        if self.held[1] > keep:
            self.held[0].give_back(self.held[1] - keep)
            self.held[1] = keep
            _set_numba_threads_here(keep)
            _task.budget = keep

    def take_back(self) -> None:
        if self.held is None or self.held[1] >= self.count:
            return
        self.held[1] += self.held[0].take_up_to(self.count - self.held[1])
        _set_numba_threads_here(self.held[1])
        _task.budget = self.held[1]


def _task_threads(per_task: Callable[[T], int] | int, item: T, ceiling: int) -> int:
    wanted = per_task(item) if callable(per_task) else per_task
    return max(1, min(int(wanted), max(ceiling, 1)))


def iter_ahead(
    items: Iterable[T],
    *,
    depth: int = 1,
    consumer_threads: int = 1,
    min_threads: int = 2,
    name: str = "semantic3d-ahead",
) -> Iterator[T]:
    """The items of ``items``, produced on a thread of their own up to ``depth`` ahead.

    The producer's work (parsing a file, casting rays) then overlaps the consumer's
    (binning, formatting, writing); the items and their order are those of ``items``. The
    budget is split: the consumer's numba kernels run on ``consumer_threads`` threads
    while it handles an item, the producer's on the rest. With a budget below
    ``min_threads`` nothing overlaps (the items are produced in the caller's thread, each
    side on the whole budget in turn: for a producer far heavier than its consumer, two
    threads are better spent both on the producer). An exception of the
    producer is raised here when its turn comes; when the consumer stops early (or
    fails), the producer stops after its current item.
    """
    slots: queue.Queue[tuple[int, object]] = queue.Queue(maxsize=max(1, depth))
    stop = threading.Event()

    budget = thread_budget()  # the caller's (a task's share inside a task)
    if budget < max(2, min_threads) or not concurrent_kernels_supported():  # in turn
        yield from items
        return
    consumer_threads = max(1, min(int(consumer_threads), budget - 1))
    iterator = iter(items)

    def produce() -> None:
        try:
            with numba_threads(budget - consumer_threads):
                for item in iterator:
                    slots.put((_ITEM, item))
                    if stop.is_set():
                        break
                else:
                    slots.put((_DONE, None))
        except BaseException as exc:  # handed to the consumer
            slots.put((_FAILED, exc))
        finally:
            if stop.is_set():  # the consumer left: release the producer's resources here
                close = getattr(iterator, "close", None)
                if close is not None:
                    close()

    thread = threading.Thread(target=produce, name=name, daemon=True)
    thread.start()
    try:
        while True:
            kind, value = slots.get()
            if kind == _DONE:
                return
            if kind == _FAILED:
                assert isinstance(value, BaseException)
                raise value
            with numba_threads(consumer_threads):  # the consumer's share while it works
                yield value  # type: ignore[misc]
    finally:
        stop.set()
        while thread.is_alive():  # unblock a producer waiting for a free slot
            with suppress(queue.Empty):
                slots.get(timeout=0.05)
        thread.join()


_ITEM, _DONE, _FAILED = range(3)


@contextmanager
def thread_limit(n_threads: int | None) -> Iterator[int]:
    """:func:`set_thread_limit` for the block; the previous limit is back afterwards.

    Yields the budget in force inside the block.
    """
    previous = _limit
    budget = set_thread_limit(n_threads)
    try:
        yield budget
    finally:
        set_thread_limit(previous)
