"""The evaluation worker: lease a job, evaluate it with heartbeats, record the result.

Run one with ``semantic3d worker`` (any number, on any machine sharing the database and
the data dir), or in the server process (``serve`` does so on SQLite). Scoring is
:func:`semantic3d.evaluation.evaluate_submission`, the very function the CLI uses.
"""

from __future__ import annotations

import logging
import os
import secrets
import socket
import threading
import time

from sqlalchemy.orm import Session, sessionmaker

from semantic3d.core.errors import Semantic3DError
from semantic3d.core.threads import thread_limit
from semantic3d.evaluation import evaluate_submission
from semantic3d.server.models import Submission
from semantic3d.server.services import queue
from semantic3d.server.services.challenges import ChallengeCache
from semantic3d.server.services.methods import method_of
from semantic3d.server.services.scores import stored_scores
from semantic3d.server.services.uploads import expire_uploads
from semantic3d.server.settings import Settings

logger = logging.getLogger(__name__)


class LeaseLostError(Exception):
    """Raised inside an evaluation whose lease was lost or that must stop; not a bug."""


def new_worker_id() -> str:
    """A worker id unique across hosts and processes: ``host:pid:random``."""
    return f"{socket.gethostname()[:60]}:{os.getpid()}:{secrets.token_hex(3)}"


class _Heartbeat(threading.Thread):
    """Renews a lease every third of its length and publishes progress while a job runs."""

    def __init__(
        self, factory: sessionmaker[Session], settings: Settings, lease: queue.Lease
    ) -> None:
        super().__init__(name=f"heartbeat-{lease.job_id}", daemon=True)
        self._factory = factory
        self._settings = settings
        self._lease = lease
        self._stop_event = threading.Event()
        self.done = 0
        self.total = 0
        self.lost = False

    def run(self) -> None:
        interval = max(0.2, self._settings.job_lease_s / 3)
        while not self._stop_event.wait(interval):
            try:
                if not queue.renew(
                    self._factory, self._settings, self._lease, done=self.done, total=self.total
                ):
                    logger.warning("job %d: lease lost", self._lease.job_id)
                    self.lost = True
                    return
            except Exception:  # a database hiccup: try again at the next beat
                logger.exception("job %d: heartbeat failed", self._lease.job_id)

    def stop(self) -> None:
        self._stop_event.set()
        self.join(timeout=30)


class Worker:
    """Evaluates queued submissions one at a time.

    ``run_once()`` sweeps, leases at most one job and evaluates it; ``run(stop)`` loops
    until ``stop`` is set. A job interrupted by ``stop`` is released for another worker.
    """

    def __init__(
        self,
        settings: Settings,
        factory: sessionmaker[Session],
        *,
        cache: ChallengeCache | None = None,
        worker_id: str | None = None,
    ) -> None:
        self.settings = settings
        self.factory = factory
        self.cache = cache or ChallengeCache(settings)
        self.worker_id = worker_id or new_worker_id()
        self._stop = threading.Event()
        self._last_sweep = 0.0

    def run(self, stop: threading.Event | None = None) -> None:
        """Process jobs until ``stop`` is set (or forever)."""
        if stop is not None:
            self._stop = stop
        logger.info("worker %s started", self.worker_id)
        while not self._stop.is_set():
            try:
                worked = self.run_once()
            except Exception:
                logger.exception("worker %s: unexpected error; continuing", self.worker_id)
                worked = False
            if not worked:
                self._stop.wait(self.settings.worker_poll_s)
        logger.info("worker %s stopped", self.worker_id)

    def run_once(self) -> bool:
        """Sweep (at most every ~30 s), then evaluate one job; whether a job was taken."""
        if time.monotonic() - self._last_sweep > 30:
            self._last_sweep = time.monotonic()
            # Expired uploads first: deleting their files frees space even on a full disk,
            # where the queue sweep (a database write) would fail.
            for chore in (expire_uploads, queue.sweep):
                try:
                    chore(self.factory, self.settings)
                except Exception:
                    logger.exception("worker %s: %s failed", self.worker_id, chore.__name__)
        lease = queue.lease_next(self.factory, self.settings, self.worker_id)
        if lease is None:
            return False
        self._process(lease)
        return True

    def _process(self, lease: queue.Lease) -> None:
        with self.factory() as session:
            submission = session.get(Submission, lease.submission_id)
            if submission is None:  # deleted meanwhile
                return
            challenge_row = submission.challenge
            method = method_of(submission)
            path = self.settings.submissions_dir / submission.stored_name
            filename = submission.filename
        heartbeat = _Heartbeat(self.factory, self.settings, lease)
        heartbeat.start()

        def progress(done: int, total: int) -> None:
            heartbeat.done, heartbeat.total = int(done), int(total)
            if heartbeat.lost or self._stop.is_set():
                raise LeaseLostError

        try:
            challenge = self.cache.get(challenge_row)
            with thread_limit(self.settings.evaluation_thread_budget):
                result = evaluate_submission(
                    path, challenge=challenge, method=method, progress=progress
                )
        except LeaseLostError:
            heartbeat.stop()
            if not heartbeat.lost:
                queue.release(self.factory, lease)
                logger.info("job %d released: worker stopping", lease.job_id)
            return
        except Semantic3DError as exc:
            heartbeat.stop()
            message = str(exc).replace(str(path), filename)
            message = message.replace(str(self.settings.data_dir), "<data>")
            queue.fail(self.factory, lease, message)
            return
        except Exception:
            heartbeat.stop()
            logger.exception("job %d: evaluation crashed", lease.job_id)
            queue.fail(self.factory, lease, "internal error while evaluating (see the server log)")
            return
        heartbeat.stop()
        if heartbeat.lost:
            return
        stored = queue.complete(
            self.factory,
            lease,
            scores=stored_scores(result),
            progress_total=max(heartbeat.total, 1),
        )
        if not stored:
            logger.warning("job %d: finished after losing its lease; result dropped", lease.job_id)


class WorkerThread:
    """A :class:`Worker` on a daemon thread (the server's embedded worker)."""

    def __init__(self, worker: Worker) -> None:
        self.worker = worker
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=worker.run, args=(self._stop,), name="semantic3d-worker", daemon=True
        )

    def start(self) -> None:
        """Start processing jobs."""
        self._thread.start()

    def stop(self, timeout_s: float = 30.0) -> None:
        """Ask the worker to stop (a running job is released) and wait for it."""
        self._stop.set()
        self._thread.join(timeout=timeout_s)
