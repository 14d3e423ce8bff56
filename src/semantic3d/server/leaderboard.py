"""Leaderboards: published, evaluated submissions of a challenge, ranked server-side.

Ranking: mean IoU (descending), then overall accuracy (descending), then the earlier
submission first. Public rows carry the method card and the overall scores only; the
per-scan scores of a result are never part of them. Rows, the JSON form and the
page as anonymous visitors see it are cached per challenge for ``leaderboard_cache_s``
seconds (and dropped at once when this process publishes a submission), so a popular
board costs one query every few seconds.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Any, TypeVar

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.core.classes import CLASSES
from semantic3d.server.challenges import get_challenge
from semantic3d.server.models import Challenge, Submission, User

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class LeaderboardEntry:
    """One public row of a leaderboard."""

    rank: int
    submission_id: int
    method: str
    submitted_by: str
    mean_iou: float | None
    overall_accuracy: float | None
    iou: tuple[float | None, ...]
    runtime_s: float | None
    hardware: str | None
    submitted_at: datetime
    paper_url: str
    code_url: str


def challenge_dict(challenge: Challenge) -> dict[str, object]:
    """Public JSON view of a challenge (never where its ground truth lives)."""
    return {
        "name": challenge.name,
        "title": challenge.title,
        "description": challenge.description,
        "kind": challenge.kind,
        "protocol_version": challenge.protocol_version,
        "n_scans": challenge.n_scans,
        "n_points": challenge.n_points,
        "open": challenge.is_open,
        "classes": [{"value": c.value, "name": c.name, "colour": c.hex_colour} for c in CLASSES],
    }


def leaderboard_entries(session: Session, challenge: Challenge) -> list[LeaderboardEntry]:
    """The ranked public rows of ``challenge`` (one query, only the columns shown)."""
    rows = session.execute(
        select(
            Submission.id,
            Submission.method_name,
            User.username,
            Submission.mean_iou,
            Submission.overall_accuracy,
            Submission.iou_json,
            Submission.runtime_s,
            Submission.hardware,
            Submission.created_at,
            Submission.paper_url,
            Submission.code_url,
        )
        .join(User, Submission.user_id == User.id)
        .where(
            Submission.challenge_id == challenge.id,
            Submission.published,
            Submission.mean_iou.is_not(None),
        )
        .order_by(
            Submission.mean_iou.desc(),
            Submission.overall_accuracy.desc(),
            Submission.created_at.asc(),
            Submission.id.asc(),
        )
    ).all()
    return [
        LeaderboardEntry(
            rank=rank,
            submission_id=row.id,
            method=row.method_name,
            submitted_by=row.username,
            mean_iou=row.mean_iou,
            overall_accuracy=row.overall_accuracy,
            iou=tuple(json.loads(row.iou_json or "[]")),
            runtime_s=row.runtime_s,
            hardware=row.hardware,
            submitted_at=row.created_at,
            paper_url=row.paper_url,
            code_url=row.code_url,
        )
        for rank, row in enumerate(rows, start=1)
    ]


def leaderboard_dict(challenge: Challenge, entries: list[LeaderboardEntry]) -> dict[str, object]:
    """JSON view of a leaderboard."""
    values = [str(c.value) for c in CLASSES]
    rows = [
        {
            "rank": entry.rank,
            "submission_id": entry.submission_id,
            "method": entry.method,
            "submitted_by": entry.submitted_by,
            "mean_iou": entry.mean_iou,
            "overall_accuracy": entry.overall_accuracy,
            "iou": dict(zip(values, entry.iou, strict=False)),
            "runtime_s": entry.runtime_s,
            "hardware": entry.hardware,
            "submitted_at": entry.submitted_at.isoformat(),
            "paper_url": entry.paper_url,
            "code_url": entry.code_url,
        }
        for entry in entries
    ]
    return {"challenge": challenge_dict(challenge), "entries": rows}


class LeaderboardCache:
    """Leaderboards (rows, JSON bytes, anonymous HTML) per challenge, kept ``ttl_s`` seconds."""

    def __init__(self, factory: sessionmaker[Session], ttl_s: float) -> None:
        self._factory = factory
        self._ttl_s = ttl_s
        self._lock = threading.Lock()
        self._cached: dict[tuple[str, str], tuple[float, Any]] = {}

    def fresh(self, kind: str, name: str) -> Any | None:
        """The cached value under ``(kind, name)`` if younger than the TTL, else ``None``."""
        with self._lock:
            hit = self._cached.get((kind, name))
        if hit is not None and time.monotonic() - hit[0] < self._ttl_s:
            return hit[1]
        return None

    def cached(self, kind: str, name: str, build: Callable[[], T]) -> T:
        """The value cached under ``(kind, name)``, built anew once it is older than the TTL."""
        now = time.monotonic()
        with self._lock:
            hit = self._cached.get((kind, name))
        if hit is not None and now - hit[0] < self._ttl_s:
            value: T = hit[1]
            return value
        value = build()
        with self._lock:
            self._cached[(kind, name)] = (now, value)
        return value

    def board(self, name: str) -> tuple[Challenge, list[LeaderboardEntry]]:
        """The challenge called ``name`` and its ranked rows (``NotFoundError`` if none)."""

        def build() -> tuple[Challenge, list[LeaderboardEntry]]:
            with self._factory() as session:
                challenge = get_challenge(session, name)
                return challenge, leaderboard_entries(session, challenge)

        return self.cached("board", name, build)

    def json_bytes(self, name: str) -> bytes:
        """The leaderboard of challenge ``name`` as JSON bytes (``NotFoundError`` if none)."""

        def build() -> bytes:
            challenge, entries = self.board(name)
            return json.dumps(leaderboard_dict(challenge, entries), separators=(",", ":")).encode()

        return self.cached("json", name, build)

    def invalidate(self, name: str | None = None) -> None:
        """Drop one challenge's cached boards (all when ``name`` is ``None``)."""
        with self._lock:
            if name is None:
                self._cached.clear()
            else:
                for key in [key for key in self._cached if key[1] == name]:
                    del self._cached[key]
