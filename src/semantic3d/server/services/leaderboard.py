"""Leaderboards: published, evaluated submissions of a challenge, ranked server-side.

Ranking: mean IoU (descending), then overall accuracy (descending), then the earlier
submission first. Public rows carry the method card and the overall scores only; the
per-scan scores of a result are never part of them. Rows, the JSON and CSV forms and the
page as anonymous visitors see it are cached per challenge for ``leaderboard_cache_s``
seconds (and dropped at once when this process publishes a submission), so a popular
board costs one query every few seconds.

The boards of ``semantic-8`` and ``reduced-8`` also show the paper's published results
(:mod:`semantic3d.server.references`): sorted in by mean IoU for comparison, marked as
references and never ranked, so the ranks count participants only.
"""

from __future__ import annotations

import csv
import io
import math
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
from semantic3d.server.references import ReferenceResult, reference_results
from semantic3d.server.schemas import (
    ChallengeInfo,
    ClassInfo,
    Leaderboard,
    LeaderboardRow,
    ReferenceSource,
)
from semantic3d.server.services.challenges import (
    accepts_submissions,
    get_challenge,
    shows_confusion,
    submission_status,
)
from semantic3d.server.services.scores import stored_iou

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class LeaderboardEntry:
    """One public row of a leaderboard: a participant's submission or a reference result.

    Reference rows (``reference=True``) have no rank, submission or date; their
    ``submitted_by`` names the publication and ``paper_url`` links to it.
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
        hardware=None,
        submitted_at=None,
        paper_url=result.source.url,
        code_url="",
        reference=True,
    )


def reference_entries(challenge: ChallengeRecord) -> list[LeaderboardEntry]:
    """The reference rows of ``challenge`` (the paper's, for semantic-8 and reduced-8)."""
    return [reference_entry(result) for result in reference_results().for_challenge(challenge.kind)]


def merged_rows(
    entries: list[LeaderboardEntry], references: list[LeaderboardEntry]
) -> list[LeaderboardEntry]:
    """Participants in rank order with the references sorted in by mean IoU.

    A reference goes below participants of equal mean IoU; references without a mean IoU
    go last.
    """
    rows = list(entries)
    for ref in sorted(references, key=_reference_order):
        if ref.mean_iou is None:
            rows.append(ref)
            continue
        at = len(rows)
        for index, row in enumerate(rows):
            if row.mean_iou is None or row.mean_iou < ref.mean_iou:
                at = index
                break
        rows.insert(at, ref)
    return rows


def _reference_order(entry: LeaderboardEntry) -> tuple[float, float]:
    return (
        -(entry.mean_iou if entry.mean_iou is not None else -math.inf),
        -(entry.overall_accuracy if entry.overall_accuracy is not None else -math.inf),
    )


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


def leaderboard_row(entry: LeaderboardEntry) -> LeaderboardRow:
    """The API's view of one row: ``iou`` keyed by label value."""
    values = [str(c.value) for c in CLASSES]
    return LeaderboardRow(
        rank=entry.rank,
        reference=entry.reference,
        submission_id=entry.submission_id,
        method=entry.method,
        submitted_by=entry.submitted_by,
        mean_iou=entry.mean_iou,
        overall_accuracy=entry.overall_accuracy,
        iou=dict(zip(values, entry.iou, strict=False)),
        runtime_s=entry.runtime_s,
        hardware=entry.hardware,
        submitted_at=entry.submitted_at,
        paper_url=entry.paper_url,
        code_url=entry.code_url,
    )


def leaderboard(challenge: ChallengeRecord, entries: list[LeaderboardEntry]) -> Leaderboard:
    """The API's view of a leaderboard: ranked ``entries``, apart the unranked ``references``.

    Scores are fractions (0..1); ``iou`` maps label values to IoU (``null``: unknown, or
    class absent); ``runtime_s`` is the run time T the authors report.
    """
    references = reference_entries(challenge)
    source = reference_results().source
    return Leaderboard(
        challenge=challenge_info(challenge),
        entries=[leaderboard_row(entry) for entry in entries],
        references=[leaderboard_row(entry) for entry in references],
        reference_source=(
            ReferenceSource(citation=source.citation, url=source.url, label=source.label)
            if references
            else None
        ),
    )


CSV_COLUMNS = (
    "rank",
    "kind",
    "method",
    "submitted_by",
    "mean_iou",
    "overall_accuracy",
    *(f"iou_{c.name.replace('-', '_').replace(' ', '_')}" for c in CLASSES),
    "runtime_s",
    "hardware",
    "submitted_at",
    "paper_url",
    "code_url",
    "submission_id",
)
"""Header of the CSV export: one row per participant or reference, scores as fractions."""

_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def _csv_text(value: str | None) -> str:
    """Text for a spreadsheet cell; a leading formula character is neutralised with ``'``."""
    if not value:
        return ""
    return f"'{value}" if value.startswith(_FORMULA_START) else value


def _csv_number(value: float | int | None) -> str:
    return "" if value is None else repr(value)


def leaderboard_csv(challenge: ChallengeRecord, entries: list[LeaderboardEntry]) -> str:
    """The board as CSV, in the order of the page (references sorted in, without rank)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\r\n")
    writer.writerow(CSV_COLUMNS)
    for entry in merged_rows(entries, reference_entries(challenge)):
        writer.writerow(
            [
                _csv_number(entry.rank),
                "reference" if entry.reference else "participant",
                _csv_text(entry.method),
                _csv_text(entry.submitted_by),
                _csv_number(entry.mean_iou),
                _csv_number(entry.overall_accuracy),
                *(_csv_number(value) for value in entry.iou),
                _csv_number(entry.runtime_s),
                _csv_text(entry.hardware),
                entry.submitted_at.isoformat() if entry.submitted_at else "",
                _csv_text(entry.paper_url),
                _csv_text(entry.code_url),
                _csv_number(entry.submission_id),
            ]
        )
    return buffer.getvalue()


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

        def build() -> bytes:
            challenge, entries = self.board(name)
            return leaderboard(challenge, entries).model_dump_json().encode()

        return self.cached("json", name, build)

    def csv_bytes(self, name: str) -> bytes:
        """The leaderboard of challenge ``name`` as UTF-8 CSV (``NotFoundError`` if none)."""

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
