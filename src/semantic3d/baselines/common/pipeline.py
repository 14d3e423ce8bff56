"""A producer thread with a bounded queue: the next items are made while the caller works.

:class:`Prefetched` runs an iterator in a thread and hands its items over through a queue
of ``depth`` places, so the producer runs at most ``depth + 1`` items ahead. It serves
the CNN's labelling loop (the next batch's cubes while the network classifies this one)
and the networks' training (round ``r + 1``'s cubes or sub-clouds while round ``r``
trains). The producer's work is numba kernels and torch operations, which release the
GIL, so it truly overlaps. Needs torch (the networks' extras).

On a CUDA device the producer issues its work on a stream of its own: each item is
handed over with an event the consumer's stream waits on (the consumer never waits on the
host), and its tensors are marked as used by the consumer's stream, so the caching
allocator does not reuse their memory early.

An error in the producer is raised in the consumer at the item where it happened;
:meth:`Prefetched.close` (also on leaving the ``with`` block, and when the consumer stops
early or is interrupted) stops the producer and waits for it.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator
from typing import Any, Generic, TypeVar

from semantic3d.core.errors import require

torch: Any = require("torch", "torch")

__all__ = ["Prefetched"]

T = TypeVar("T")

_POLL_S = 0.1


class _Failure:
    def __init__(self, error: BaseException) -> None:
        self.error = error


_DONE = object()


class Prefetched(Generic[T]):
    """Items of ``produce()``, made in a thread, ``depth`` of them queued at most.

    Args:
        produce: called once in the producer thread; returns the iterator of items.
        depth: places in the queue (>= 1).
        device: the torch device the items' tensors live on (a CUDA device gets the
            stream handover described in the module docstring).
        name: the thread's name.
    """

    def __init__(
        self,
        produce: Callable[[], Iterator[T]],
        *,
        depth: int = 2,
        device: Any = "cpu",
        name: str = "prefetch",
    ) -> None:
        self._produce = produce
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=max(depth, 1))
        self._stop = threading.Event()
        self._device = torch.device(device)
        self._cuda = self._device.type == "cuda"
        self._stream = torch.cuda.Stream(device=self._device) if self._cuda else None
        self._finished = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    # -- producer -----------------------------------------------------------------------
    def _run(self) -> None:
        try:
            if self._stream is not None:
                with torch.cuda.device(self._device), torch.cuda.stream(self._stream):
                    self._feed()
            else:
                self._feed()
        except BaseException as error:  # handed to the consumer, raised there
            self._put(_Failure(error))
        else:
            self._put(_DONE)

    def _feed(self) -> None:
        items = self._produce()
        try:
            for item in items:
                event = None
                if self._stream is not None:
                    event = torch.cuda.Event()
                    event.record(self._stream)
                if not self._put((item, event)):
                    return
        finally:
            close = getattr(items, "close", None)
            if close is not None:  # a generator's cleanup runs here, in its thread
                close()

    def _put(self, value: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(value, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    # -- consumer -----------------------------------------------------------------------
    def poll(self, timeout_s: float) -> tuple[bool, T | None]:
        """``(True, item)`` when an item arrives within ``timeout_s``, ``(False, None)``
        otherwise; raises ``StopIteration`` at the end and the producer's error."""
        if self._finished:
            raise StopIteration
        try:
            value = self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return False, None
        if value is _DONE:
            self._finished = True
            raise StopIteration
        if isinstance(value, _Failure):
            self._finished = True
            raise value.error
        item, event = value
        if event is not None:
            stream = torch.cuda.current_stream(self._device)
            stream.wait_event(event)
            _record_stream(item, stream)
        return True, item

    def __iter__(self) -> Iterator[T]:
        return self

    def __next__(self) -> T:
        while True:
            arrived, item = self.poll(_POLL_S)
            if arrived:
                return item  # type: ignore[return-value]

    def close(self) -> None:
        """Stop the producer (it ends at its next item) and wait for it."""
        self._stop.set()  # a producer blocked on a full queue sees it within _POLL_S
        self._thread.join()

    def __enter__(self) -> Prefetched[T]:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _record_stream(item: Any, stream: Any, depth: int = 0) -> None:
    """Mark the CUDA tensors of ``item`` (a tensor, or tuples / lists / dicts / objects with
    ``__slots__`` or ``__dict__`` holding them, nested) as used by ``stream``."""
    if isinstance(item, torch.Tensor):
        if item.is_cuda:
            item.record_stream(stream)
        return
    if depth > 8 or item is None or isinstance(item, str | bytes | int | float | bool):
        return
    if isinstance(item, tuple | list):
        parts: Any = item
    elif isinstance(item, dict):
        parts = item.values()
    else:
        names = getattr(item, "__slots__", None) or list(getattr(item, "__dict__", {}))
        parts = [getattr(item, name, None) for name in names]
    for part in parts:
        _record_stream(part, stream, depth + 1)
