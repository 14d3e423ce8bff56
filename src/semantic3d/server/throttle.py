"""In-memory sliding-window rate limits (registrations per address, rejected uploads).

Kept per server process: enough for the embedded single-process server; with several
web processes each counts on its own (the limits then multiply by their number). A
restart forgets them, which only ever lets an honest user in sooner.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from semantic3d.server.errors import ThrottledError

_MAX_KEYS = 100_000


class RateLimiter:
    """At most ``limit`` events per key within ``window_s`` seconds.

    ``check(key)`` raises :class:`ThrottledError` (with the seconds until the oldest event
    leaves the window) when the key is at its limit; ``hit(key)`` records an event.
    """

    def __init__(
        self, limit: int, window_s: float, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.limit = limit
        self.window_s = window_s
        self._clock = clock
        self._events: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def _recent(self, key: str, now: float) -> deque[float]:
        events = self._events.get(key)
        if events is None:
            return deque()
        while events and events[0] <= now - self.window_s:
            events.popleft()
        if not events:
            del self._events[key]
        return events

    def count(self, key: str) -> int:
        """Events of ``key`` within the window."""
        with self._lock:
            return len(self._recent(key, self._clock()))

    def check(self, key: str, what: str) -> None:
        """Raise :class:`ThrottledError` if ``key`` is at its limit (``what`` names it)."""
        with self._lock:
            now = self._clock()
            events = self._recent(key, now)
            if len(events) < self.limit:
                return
            retry_s = max(1, math.ceil(events[0] + self.window_s - now))
        raise ThrottledError(
            f"too many {what}: {len(events)} in the last {_duration(self.window_s)} "
            f"(at most {self.limit}); try again in {retry_s} s",
            retry_after_s=retry_s,
        )

    def hit(self, key: str) -> None:
        """Record one event of ``key``."""
        with self._lock:
            self._append(key, self._clock())

    def check_and_hit(self, key: str, what: str) -> None:
        """:meth:`check`, then :meth:`hit` if allowed, as one step."""
        with self._lock:
            now = self._clock()
            if len(self._recent(key, now)) < self.limit:
                self._append(key, now)
                return
        self.check(key, what)

    def _append(self, key: str, now: float) -> None:
        if key not in self._events and len(self._events) >= _MAX_KEYS:
            for stale in list(self._events):
                self._recent(stale, now)  # drops keys with no event left in the window
        self._events.setdefault(key, deque()).append(now)


def limiter_in(store: dict[str, Any], name: str, *, limit: int, window_s: float) -> RateLimiter:
    """The :class:`RateLimiter` kept under ``name`` in ``store`` (created on first use)."""
    limiter = store.get(name)
    if not isinstance(limiter, RateLimiter):
        limiter = store.setdefault(name, RateLimiter(limit, window_s))
    return limiter


def _duration(seconds: float) -> str:
    if seconds >= 3600 and seconds % 3600 == 0:
        return f"{seconds / 3600:g} h"
    if seconds >= 60:
        return f"{seconds / 60:g} min"
    return f"{seconds:g} s"
