"""Challenges and their leaderboards: ``/``, ``/challenges/{name}`` (and ``.csv``), the API."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, Response

from semantic3d.server.challenges import (
    CONFUSION_MIN_SCANS,
    NOT_INSTALLED,
    get_challenge,
    list_challenges,
    shows_confusion,
)
from semantic3d.server.leaderboard import challenge_dict, merged_rows, reference_entries
from semantic3d.server.references import reference_results
from semantic3d.server.web import render, session_user, state_of

router = APIRouter()


@router.get("/api/challenges", tags=["challenges"])
def api_challenges(request: Request) -> dict[str, Any]:
    """Every challenge of this server."""
    rows = list_challenges(state_of(request).factory)
    return {"challenges": [challenge_dict(row) for row in rows]}


@router.get("/api/challenges/{name}", tags=["challenges"])
def api_challenge(request: Request, name: str) -> dict[str, Any]:
    """One challenge."""
    with state_of(request).factory() as session:
        return challenge_dict(get_challenge(session, name))


@router.get("/api/challenges/{name}/leaderboard", tags=["challenges"])
async def api_leaderboard(request: Request, name: str) -> Response:
    """The public leaderboard, ranked by mean IoU (cached for a few seconds)."""
    cache = state_of(request).leaderboards
    # The hot path answers from memory on the event loop; only a rebuild goes to a thread.
    body = cache.fresh("json", name)
    if body is None:
        body = await run_in_threadpool(cache.json_bytes, name)
    return Response(body, media_type="application/json")


@router.get("/challenges/{name}/leaderboard.csv", tags=["challenges"])
async def leaderboard_csv(request: Request, name: str) -> Response:
    """The public leaderboard as CSV: participants ranked, references sorted in unranked."""
    cache = state_of(request).leaderboards
    body = cache.fresh("csv", name)
    if body is None:
        body = await run_in_threadpool(cache.csv_bytes, name)
    return Response(
        body,
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{name}-leaderboard.csv"'},
    )


@router.get("/", include_in_schema=False)
def index_page(request: Request) -> Response:
    request.state.user = session_user(request)
    rows = list_challenges(state_of(request).factory)
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
    return render(
        request,
        "leaderboard.html",
        {
            "challenge": challenge,
            "entries": merged_rows(entries, references),
            "n_participants": len(entries),
            "reference_source": reference_results().source if references else None,
            "not_installed": NOT_INSTALLED,
            "confusion_min_scans": CONFUSION_MIN_SCANS,
            "shows_confusion": shows_confusion(challenge),
        },
    )
