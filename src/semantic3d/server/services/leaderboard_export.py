"""A leaderboard as the API's JSON and as CSV: the same rows, in the page's order.

The JSON (:func:`leaderboard`) keeps ranked participants (``entries``) and unranked
references apart, each row with its ``position`` on the page; the CSV
(:func:`leaderboard_csv`) has one line per row in that order. Both hold scores as
fractions at full precision (the page shows them in per cent), every row's tag, source and
method page.
"""

from __future__ import annotations

import csv
import io

from semantic3d.core.classes import CLASSES
from semantic3d.server.models import ChallengeRecord
from semantic3d.server.references import reference_results
from semantic3d.server.schemas import Leaderboard, LeaderboardRow, ReferenceSource
from semantic3d.server.services.leaderboard import (
    LeaderboardEntry,
    challenge_info,
    merged_rows,
    method_page,
    reference_entries,
)


def _source(entry: LeaderboardEntry) -> ReferenceSource | None:
    if entry.source is None:
        return None
    source = entry.source
    return ReferenceSource(
        citation=source.citation, url=source.url, label=source.label, year=source.year
    )


def leaderboard_row(challenge: str, entry: LeaderboardEntry, position: int) -> LeaderboardRow:
    """The API's view of one row: ``iou`` and ``iou_notes`` keyed by label value."""
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
        tag=entry.tag,
        position=position,
        method_page=method_page(challenge, entry),
        source=_source(entry),
        table=entry.table,
        iou_notes={v: note for v, note in zip(values, entry.iou_notes, strict=False) if note},
        description=entry.description,
        note=entry.note,
    )


def leaderboard(challenge: ChallengeRecord, entries: list[LeaderboardEntry]) -> Leaderboard:
    """The API's view of a leaderboard: ranked ``entries``, apart the unranked ``references``.

    Scores are fractions (0..1); ``iou`` maps label values to IoU (``null``: unknown, or
    class absent); ``runtime_s`` is the run time T the authors report.
    """
    references = reference_entries(challenge)
    position = {id(row): index for index, row in enumerate(merged_rows(entries, references), 1)}
    source = reference_results().benchmark_source
    return Leaderboard(
        challenge=challenge_info(challenge),
        entries=[leaderboard_row(challenge.name, e, position[id(e)]) for e in entries],
        references=[leaderboard_row(challenge.name, e, position[id(e)]) for e in references],
        reference_source=(
            ReferenceSource(
                citation=source.citation, url=source.url, label=source.label, year=source.year
            )
            if references
            else None
        ),
    )


def iou_column(name: str) -> str:
    """The CSV column of a class's IoU: ``iou_`` and the name with ``_`` for separators.

    >>> iou_column("man-made terrain")
    'iou_man_made_terrain'
    """
    return "iou_" + name.replace("-", "_").replace(" ", "_")


CSV_COLUMNS = (
    "rank",
    "position",
    "kind",
    "tag",
    "method",
    "submitted_by",
    "mean_iou",
    "overall_accuracy",
    *(iou_column(c.name) for c in CLASSES),
    "runtime_s",
    "hardware",
    "submitted_at",
    "paper_url",
    "code_url",
    "source",
    "source_year",
    "source_url",
    "method_page",
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
    for position, entry in enumerate(merged_rows(entries, reference_entries(challenge)), 1):
        source = entry.source
        writer.writerow(
            [
                _csv_number(entry.rank),
                str(position),
                "reference" if entry.reference else "participant",
                entry.tag,
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
                _csv_text(source.citation) if source else "",
                str(source.year) if source else "",
                _csv_text(source.url) if source else "",
                method_page(challenge.name, entry),
                _csv_number(entry.submission_id),
            ]
        )
    return buffer.getvalue()
