"""Spans of work on a timeline: which step of a job ran on which thread, and when.

A job's steps mark themselves with :func:`span` (a tile's features, its forest, its graph
cut, one square of that cut, ...). Nothing is recorded unless a :func:`recording` block is
open, and then every span that ends inside it, on any thread, is kept with its thread,
its wall-clock start and end, the CPU time of its thread (a compiled kernel's own worker
threads are not counted) and the attributes it was given.

What it is for: a job that scales badly across cores spends its last seconds on a few
threads, and sampled stacks say which code runs then but not which tile's chain of steps
made everyone wait. The spans say that: when the last tile started, which step of which
tile ended last, how long the cuts of the largest squares took.

The cost when not recording is one global read per span; spans mark steps of
milliseconds or more, never per-point work.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

__all__ = ["Span", "Timeline", "inside", "open_span", "recording", "span"]


@dataclass(frozen=True, slots=True)
class Span:
    """One step: its name, thread, start and end (seconds since the recording began), the
    CPU seconds of its thread meanwhile and its attributes. Spans are numbered as they
    start (``number``); ``parent`` is the number of the span it ran inside on the same
    thread, or -1."""

    name: str
    thread: str
    start_s: float
    end_s: float
    cpu_s: float
    attrs: dict[str, Any] = field(default_factory=dict)
    number: int = -1
    parent: int = -1

    @property
    def wall_s(self) -> float:
        """Wall-clock seconds from its start to its end."""
        return self.end_s - self.start_s

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        return {
            "name": self.name,
            "thread": self.thread,
            "start_s": round(self.start_s, 6),
            "end_s": round(self.end_s, 6),
            "cpu_s": round(self.cpu_s, 6),
            "attrs": self.attrs,
            "number": self.number,
            "parent": self.parent,
        }


class Timeline:
    """The spans recorded by one :func:`recording` block and, once it ended, its length."""

    def __init__(self) -> None:
        self._origin = time.perf_counter()
        self._lock = threading.Lock()
        self._spans: list[Span] = []
        self._started = 0
        self.end_s: float | None = None

    def _number(self) -> int:
        with self._lock:
            number = self._started
            self._started += 1
        return number

    def _add(self, finished: Span) -> None:
        with self._lock:
            if self.end_s is None:  # a span that outlives the recording is not kept
                self._spans.append(finished)

    def _end(self) -> None:
        with self._lock:
            self.end_s = self.now()

    def now(self) -> float:
        """Seconds since the recording began."""
        return time.perf_counter() - self._origin

    @property
    def spans(self) -> list[Span]:
        """The spans so far, by start time."""
        with self._lock:
            return sorted(self._spans, key=lambda s: (s.start_s, s.number))

    def named(self, name: str) -> list[Span]:
        """The spans called ``name``, by start time."""
        return [s for s in self.spans if s.name == name]


_active: Timeline | None = None
_recording_lock = threading.Lock()
_stack = threading.local()  # each thread's open spans (their numbers): the parent of the next


@contextmanager
def recording() -> Iterator[Timeline]:
    """Record every span that ends while the block runs, on any thread.

    Raises:
        RuntimeError: a recording is already open (one job's timeline at a time).
    """
    global _active
    with _recording_lock:
        if _active is not None:
            raise RuntimeError("a timeline is already being recorded")
        timeline = _active = Timeline()
    try:
        yield timeline
    finally:
        timeline._end()
        with _recording_lock:
            _active = None


def open_span() -> int:
    """The number of the innermost span open in this thread (-1: none, or no recording)."""
    if _active is None:
        return -1
    open_spans: list[int] | None = getattr(_stack, "open", None)
    return open_spans[-1] if open_spans else -1


@contextmanager
def inside(parent: int) -> Iterator[None]:
    """Spans begun in this thread during the block are children of span ``parent``,
    opened in another thread (:func:`open_span` there): a step's work handed to a thread
    pool stays under that step. Nothing changes for ``parent`` -1 or when not recording."""
    if parent < 0 or _active is None:
        yield
        return
    before = getattr(_stack, "open", None)
    _stack.open = [parent]
    try:
        yield
    finally:
        _stack.open = before


@contextmanager
def span(name: str, **attrs: Any) -> Iterator[dict[str, Any]]:
    """Mark the block as one step called ``name``, with ``attrs`` (JSON-ready values).

    Yields the attributes' dict: the block may add what it learns (rows, groups). Records
    nothing unless a :func:`recording` block is open.
    """
    timeline = _active
    if timeline is None:
        yield attrs
        return
    number = timeline._number()
    open_spans: list[int] | None = getattr(_stack, "open", None)
    if open_spans is None:
        open_spans = _stack.open = []
    parent = open_spans[-1] if open_spans else -1
    open_spans.append(number)
    start = timeline.now()
    cpu = time.thread_time()
    try:
        yield attrs
    finally:
        cpu_s = time.thread_time() - cpu
        end = timeline.now()
        open_spans.pop()
        timeline._add(
            Span(
                name,
                threading.current_thread().name,
                start,
                end,
                cpu_s,
                dict(attrs),
                number,
                parent,
            )
        )
