"""Progress and cancellation of the operation a session is running.

An operation reports how many points it has passed (``update``) after each block; the
page polls :meth:`OperationProgress.snapshot` (``GET /api/progress``) and may ask to
cancel (``POST /api/cancel``). Cancelling is honoured at the next block, as long as the
operation has not reached its commit (the journal write): an operation either completes
or leaves nothing behind.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from semantic3d.labelling.errors import OperationCancelledError

__all__ = ["OperationProgress"]


class OperationProgress:
    """The state of the running operation, read and cancelled from other threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._cancel = threading.Event()
        self._name: str | None = None
        self._done = 0
        self._total = 0
        self._started = 0.0
        self._cancellable = False

    def start(self, name: str, total: int) -> None:
        """A new operation begins (a cancel asked before it is forgotten)."""
        with self._lock:
            self._cancel.clear()
            self._name, self._done, self._total = name, 0, total
            self._started = time.monotonic()
            self._cancellable = True

    def set_total(self, total: int) -> None:
        """The operation found how many points it will pass (a cancel asked stays asked)."""
        with self._lock:
            self._done, self._total = 0, total

    def update(self, done: int) -> None:
        """``done`` points passed; raises :class:`OperationCancelledError` when asked to stop."""
        with self._lock:
            self._done = done
        if self._cancel.is_set() and self._cancellable:
            raise OperationCancelledError(f"{self._name}: cancelled, nothing changed")

    def committing(self) -> None:
        """The operation writes its result now: it can no longer be cancelled."""
        if self._cancel.is_set():
            raise OperationCancelledError(f"{self._name}: cancelled, nothing changed")
        with self._lock:
            self._cancellable = False

    def finish(self) -> None:
        with self._lock:
            self._name = None
            self._cancellable = False
            self._cancel.clear()

    def cancel(self) -> bool:
        """Ask the running operation to stop; ``False`` when none can be cancelled."""
        with self._lock:
            if self._name is None or not self._cancellable:
                return False
            self._cancel.set()
            return True

    def snapshot(self) -> dict[str, Any]:
        """``{running, operation, done, total, elapsed_s, cancellable}``."""
        with self._lock:
            running = self._name is not None
            return {
                "running": running,
                "operation": self._name,
                "done": self._done,
                "total": self._total,
                "elapsed_s": time.monotonic() - self._started if running else 0.0,
                "cancellable": running and self._cancellable,
            }
