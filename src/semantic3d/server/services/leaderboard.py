"""Leaderboards: published, evaluated submissions of a challenge, ranked server-side.

Ranking: mean IoU (descending), then overall accuracy (descending), then the earlier
submission first. Public rows carry the method card and the overall scores only; the
per-scan scores of a result are never part of them. Rows, the JSON and CSV forms and the
page as anonymous visitors see it are cached per challenge for ``leaderboard_cache_s``
seconds (and dropped at once when this process publishes a submission), so a popular
board costs one query every few seconds.

The boards of ``semantic-8`` and ``reduced-8`` also show reference rows
(:mod:`semantic3d.server.references`): every row of the semantic3D.net paper's tables and
later published records, sorted in by what they have (:func:`merged_rows`), tagged and
never ranked, so the ranks count participants only. Every row carries one tag
(:data:`~semantic3d.server.references.TAGS`): participants' submissions are "verified".
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Any, TypeVar

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.core.classes import CLASSES
from semantic3d.server.models import ChallengeRecord, Submission, User
from semantic3d.server.references import (
    TAG_VERIFIED,
    ReferenceResult,
    ReferenceSource,
    reference_results,
)
from semantic3d.server.schemas import ChallengeInfo, ClassInfo
from semantic3d.server.services.challenges import (
    accepts_submissions,
    get_challenge,
    shows_confusion,
    submission_status,
)
from semantic3d.server.services.scores import stored_iou

T = TypeVar("T")

_NO_NOTES = ("",) * len(CLASSES)


@dataclass(frozen=True, slots=True)
class LeaderboardEntry:
    """One public row of a leaderboard: a participant's submission or a reference result.

    Reference rows (``reference=True``) have no rank, submission or date; their
    ``submitted_by`` names the publication, ``source`` is where their values were read and
    ``reference_key`` names their method page.
    """

    rank: int | None
    submission_id: int | None
    method: str
    submitted_by: str
    mean_iou: float | None
    overall_accuracy: float | None
    iou: tuple[float | None, ...]
    runtime_s: float | None
    hardware: str | None
    submitted_at: datetime | None
    paper_url: str
    code_url: str
    reference: bool = False
    tag: str = TAG_VERIFIED
    reference_key: str | None = None
    source: ReferenceSource | None = None
    iou_notes: tuple[str, ...] = _NO_NOTES
    description: str = ""
    note: str = ""
    table: str = ""


def method_page(challenge: str, entry: LeaderboardEntry) -> str:
    """The path of ``entry``'s method page: a submission's page, or a reference's."""
    if entry.reference:
        return f"/challenges/{challenge}/references/{entry.reference_key}"
    return f"/submissions/{entry.submission_id}"


def reference_entry(result: ReferenceResult) -> LeaderboardEntry:
    """The leaderboard row of a published reference result."""
    return LeaderboardEntry(
        rank=None,
        submission_id=None,
        method=result.method,
        submitted_by=result.source.label,
        mean_iou=result.mean_iou,
        overall_accuracy=result.overall_accuracy,
        iou=result.iou,
        runtime_s=result.runtime_s,
        hardware=result.hardware,
        submitted_at=None,
        paper_url=result.paper_url,
        code_url=result.code_url,
        reference=True,
        tag=result.tag,
        reference_key=result.key,
        source=result.source,
        iou_notes=result.iou_notes,
        description=result.description,
        note=result.note,
        table=result.table,
    )


def reference_entries(challenge: ChallengeRecord) -> list[LeaderboardEntry]:
    """The reference rows of ``challenge`` (semantic-8 and reduced-8 only), file order."""
    return [reference_entry(result) for result in reference_results().for_challenge(challenge.kind)]


def merged_rows(
    entries: list[LeaderboardEntry], references: list[LeaderboardEntry]
) -> list[LeaderboardEntry]:
    """Participants in rank order with the references sorted in by what they have.

    A reference with a mean IoU goes above the first row of a lower mean IoU (so below
    participants of an equal one); one without goes by its overall accuracy among the rows
    that have one; one with neither goes last. Rows lacking the compared value are passed
    over, never pushed down: a row without a figure sorts by what it has.
    """
    rows = list(entries)
    for ref in sorted(references, key=_reference_order):
        rows.insert(_position(rows, ref), ref)
    return rows


def _position(rows: list[LeaderboardEntry], ref: LeaderboardEntry) -> int:
    for value in (_mean_iou, _overall_accuracy):
        own = value(ref)
        if own is None:
            continue
        for index, row in enumerate(rows):
            other = value(row)
            if other is not None and other < own:
                return index
        return len(rows)
    return len(rows)


def _mean_iou(entry: LeaderboardEntry) -> float | None:
    return entry.mean_iou


def _overall_accuracy(entry: LeaderboardEntry) -> float | None:
    return entry.overall_accuracy


def _reference_order(entry: LeaderboardEntry) -> tuple[bool, float, bool, float]:
    mean, accuracy = entry.mean_iou, entry.overall_accuracy
    return (mean is None, -(mean or 0.0), accuracy is None, -(accuracy or 0.0))


def challenge_info(challenge: ChallengeRecord) -> ChallengeInfo:
    """Public view of a challenge (never where its ground truth lives)."""
    return ChallengeInfo(
        name=challenge.name,
        title=challenge.title,
        description=challenge.description,
        kind=challenge.kind,
        protocol_version=challenge.protocol_version,
        n_scans=challenge.n_scans,
        n_points=challenge.n_points,
        open=challenge.is_open,
        ground_truth_installed=challenge.ground_truth_installed,
        accepts_submissions=accepts_submissions(challenge),
        status=submission_status(challenge),
        shows_confusion=shows_confusion(challenge),
        classes=[ClassInfo(value=c.value, name=c.name, colour=c.hex_colour) for c in CLASSES],
    )


def leaderboard_entries(session: Session, challenge: ChallengeRecord) -> list[LeaderboardEntry]:
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
            iou=stored_iou(row.iou_json),
            runtime_s=row.runtime_s,
            hardware=row.hardware,
            submitted_at=row.created_at,
            paper_url=row.paper_url,
            code_url=row.code_url,
        )
        for rank, row in enumerate(rows, start=1)
    ]


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

    def board(self, name: str) -> tuple[ChallengeRecord, list[LeaderboardEntry]]:
        """The challenge called ``name`` and its ranked rows (``NotFoundError`` if none)."""

        def build() -> tuple[ChallengeRecord, list[LeaderboardEntry]]:
            with self._factory() as session:
                challenge = get_challenge(session, name)
                return challenge, leaderboard_entries(session, challenge)

        return self.cached("board", name, build)

    def json_bytes(self, name: str) -> bytes:
        """The leaderboard of challenge ``name`` as JSON bytes (``NotFoundError`` if none)."""

        # The export module builds on this one's rows, hence the import here.
        from semantic3d.server.services.leaderboard_export import leaderboard

        def build() -> bytes:
            challenge, entries = self.board(name)
            return leaderboard(challenge, entries).model_dump_json().encode()

        return self.cached("json", name, build)

    def csv_bytes(self, name: str) -> bytes:
        """The leaderboard of challenge ``name`` as UTF-8 CSV (``NotFoundError`` if none)."""

        from semantic3d.server.services.leaderboard_export import leaderboard_csv

        def build() -> bytes:
            challenge, entries = self.board(name)
            return leaderboard_csv(challenge, entries).encode()

        return self.cached("csv", name, build)

    def invalidate(self, name: str | None = None) -> None:
        """Drop one challenge's cached boards (all when ``name`` is ``None``)."""
        with self._lock:
            if name is None:
                self._cached.clear()
            else:
                for key in [key for key in self._cached if key[1] == name]:
                    del self._cached[key]
