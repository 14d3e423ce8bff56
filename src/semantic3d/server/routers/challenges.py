"""Challenges and their leaderboards: ``/``, ``/challenges/{name}`` (and its ``.csv`` and
``.json`` exports), a reference row's method page, the API."""

from __future__ import annotations

from enum import Enum
from typing import Any

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, Response

from semantic3d.server.deps import DbSession, PageUser, State
from semantic3d.server.errors import NotFoundError
from semantic3d.server.references import TAG_LABELS, TAG_SHORT_LABELS, TAGS, reference_results
from semantic3d.server.schemas import ChallengeInfo, ChallengeList, Leaderboard, error_responses
from semantic3d.server.services.challenges import (
    CONFUSION_MIN_SCANS,
    NOT_INSTALLED,
    get_challenge,
    list_challenges,
    shows_confusion,
)
from semantic3d.server.services.leaderboard import (
    challenge_info,
    merged_rows,
    method_page,
    reference_entries,
    reference_entry,
)
from semantic3d.server.web import render, session_user, state_of

router = APIRouter()


_TAGS: list[str | Enum] = ["challenges"]
_ERRORS = error_responses(404, 422, 503)


@router.get("/api/challenges", response_model=ChallengeList, tags=_TAGS, responses=_ERRORS)
def api_challenges(state: State) -> ChallengeList:
    """Every challenge of this server."""
    return ChallengeList(challenges=[challenge_info(row) for row in list_challenges(state.factory)])


@router.get("/api/challenges/{name}", response_model=ChallengeInfo, tags=_TAGS, responses=_ERRORS)
def api_challenge(name: str, db: DbSession) -> ChallengeInfo:
    """One challenge."""
    return challenge_info(get_challenge(db, name))


@router.get(
    "/api/challenges/{name}/leaderboard",
    response_model=Leaderboard,
    tags=_TAGS,
    responses=_ERRORS,
)
async def api_leaderboard(name: str, state: State) -> Response:
    """The public leaderboard, ranked by mean IoU (cached for a few seconds).

    ``entries`` are the ranked participants; ``references`` the published results the
    board compares with (never ranked). Answered from the cached JSON bytes.
    """
    cache = state.leaderboards
    # The hot path answers from memory on the event loop; only a rebuild goes to a thread.
    body = cache.fresh("json", name)
    if body is None:
        body = await run_in_threadpool(cache.json_bytes, name)
    return Response(body, media_type="application/json")


@router.get(
    "/challenges/{name}/leaderboard.json",
    response_model=Leaderboard,
    tags=_TAGS,
    responses={
        404: {"content": {"text/html": {}}, "description": "no such challenge (a web page)"},
        422: {"content": {"text/html": {}}, "description": "malformed request (a web page)"},
    },
)
async def leaderboard_json(name: str, state: State) -> Response:
    """The public leaderboard as a JSON file (the body of ``/api/challenges/{name}/leaderboard``).

    A stable address to download or link the board from its page; the same bytes as the
    API route, offered as an attachment named ``{name}-leaderboard.json``.
    """
    cache = state.leaderboards
    body = cache.fresh("json", name)
    if body is None:
        body = await run_in_threadpool(cache.json_bytes, name)
    return Response(
        body,
        media_type="application/json",
        headers={"Content-Disposition": f'attachment; filename="{name}-leaderboard.json"'},
    )


@router.get(
    "/challenges/{name}/leaderboard.csv",
    response_class=Response,
    tags=_TAGS,
    responses={
        200: {"content": {"text/csv": {}}, "description": "the board as CSV"},
        404: {"content": {"text/html": {}}, "description": "no such challenge (a web page)"},
        422: {"content": {"text/html": {}}, "description": "malformed request (a web page)"},
    },
)
async def leaderboard_csv(name: str, state: State) -> Response:
    """The public leaderboard as CSV: participants ranked, references sorted in unranked.

    One line per row of the page, in its order (``position``), scores as fractions at full
    precision; columns in ``semantic3d.server.services.leaderboard_export.CSV_COLUMNS``.
    """
    cache = state.leaderboards
    body = cache.fresh("csv", name)
    if body is None:
        body = await run_in_threadpool(cache.csv_bytes, name)
    return Response(
        body,
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{name}-leaderboard.csv"'},
    )


@router.get("/", include_in_schema=False)
def index_page(request: Request, user: PageUser, state: State) -> Response:
    rows = list_challenges(state.factory)
    return render(request, "index.html", {"challenges": rows, "not_installed": NOT_INSTALLED})


@router.get("/challenges/{name}", include_in_schema=False)
async def leaderboard_page(request: Request, name: str) -> Response:
    cache = state_of(request).leaderboards
    if request.session.get("user_id") is None:
        # Anonymous visitors all get the same bytes: rendered once per cache period.
        body = cache.fresh("html", name)
        if body is None:
            body = await run_in_threadpool(_anonymous_page, request, name)
        return HTMLResponse(body)
    return await run_in_threadpool(_personal_page, request, name)


def _anonymous_page(request: Request, name: str) -> bytes:
    request.state.user = None
    cache = state_of(request).leaderboards
    return cache.cached("html", name, lambda: bytes(_render_board(request, name).body))


def _personal_page(request: Request, name: str) -> Response:
    request.state.user = session_user(request)  # the navigation bar is personal
    return _render_board(request, name)


def _render_board(request: Request, name: str) -> Any:
    challenge, entries = state_of(request).leaderboards.board(name)
    references = reference_entries(challenge)
    rows = merged_rows(entries, references)
    present = {row.tag for row in rows}
    return render(
        request,
        "leaderboard.html",
        {
            "challenge": challenge,
            "entries": rows,
            "pages": [method_page(challenge.name, row) for row in rows],
            "n_participants": len(entries),
            "tags": [(tag, TAG_LABELS[tag]) for tag in TAGS if tag in present],
            "tag_labels": TAG_LABELS,
            "tag_short_labels": TAG_SHORT_LABELS,
            "sources": _sources(references),
            "benchmark_source": reference_results().benchmark_source,
            "not_installed": NOT_INSTALLED,
            "confusion_min_scans": CONFUSION_MIN_SCANS,
            "shows_confusion": shows_confusion(challenge),
        },
    )


def _sources(references: list[Any]) -> list[Any]:
    """The distinct sources of ``references``, in order of first appearance."""
    seen: dict[str, Any] = {}
    for row in references:
        if row.source is not None:
            seen.setdefault(row.source.key, row.source)
    return list(seen.values())


@router.get("/challenges/{name}/references/{key}", include_in_schema=False)
def reference_page(request: Request, name: str, key: str, user: PageUser) -> Response:
    """A reference row's method page: source, description, links, T and per-class IoU."""
    challenge, _ = state_of(request).leaderboards.board(name)
    result = reference_results().find(challenge.kind, key)
    if result is None:
        raise NotFoundError(f"challenge {name!r} has no reference row {key!r}")
    return render(
        request,
        "reference.html",
        {
            "challenge": challenge,
            "entry": reference_entry(result),
            "tag_labels": TAG_LABELS,
            "shows_confusion": shows_confusion(challenge),
            "confusion_min_scans": CONFUSION_MIN_SCANS,
        },
    )
