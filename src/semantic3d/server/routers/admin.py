"""The admin page: queue state, every submission, requeue, open/close challenges.

Ground truth is installed from the command line (``semantic3d admin add-challenge``), never
uploaded through the web: the page says which challenges still lack it.
"""

from __future__ import annotations

from fastapi import APIRouter, Form, Request
from fastapi.responses import RedirectResponse, Response
from sqlalchemy import select

from semantic3d.server.challenges import (
    CONFUSION_MIN_SCANS,
    install_hint,
    list_challenges,
    set_challenge_open,
    set_show_confusion,
)
from semantic3d.server.errors import ForbiddenError, InvalidInputError
from semantic3d.server.models import Submission, User
from semantic3d.server.queue import queue_counts, requeue
from semantic3d.server.web import check_csrf, render, session_user, state_of

router = APIRouter(prefix="/admin", include_in_schema=False)


def _admin(request: Request) -> User:
    user = request.state.user = session_user(request)
    if user is None or not user.is_admin:
        raise ForbiddenError("this page is for administrators")
    return user


@router.get("")
def admin_page(request: Request) -> Response:
    _admin(request)
    state = state_of(request)
    with state.factory() as session:
        rows = list(session.scalars(select(Submission).order_by(Submission.id.desc()).limit(200)))
        for row in rows:
            _ = (row.job, row.challenge, row.user)
    return render(
        request,
        "admin.html",
        {
            "counts": queue_counts(state.factory),
            "submissions": rows,
            "challenges": list_challenges(state.factory),
            "install_hint": install_hint,
            "confusion_min_scans": CONFUSION_MIN_SCANS,
        },
    )


@router.post("/submissions/{submission_id}/requeue")
def admin_requeue(request: Request, submission_id: int, csrf_token: str = Form("")) -> Response:
    _admin(request)
    check_csrf(request, csrf_token)
    requeue(state_of(request).factory, submission_id)
    return RedirectResponse("/admin", status_code=303)


@router.post("/challenges/{name}/open")
def admin_open(
    request: Request, name: str, is_open: str = Form("1"), csrf_token: str = Form("")
) -> Response:
    _admin(request)
    check_csrf(request, csrf_token)
    state = state_of(request)
    set_challenge_open(state.factory, name, is_open=is_open == "1")
    state.leaderboards.invalidate(name)
    return RedirectResponse("/admin", status_code=303)


_CONFUSION_CHOICES = {"auto": None, "show": True, "hide": False}


@router.post("/challenges/{name}/confusion")
def admin_confusion(
    request: Request, name: str, show: str = Form("auto"), csrf_token: str = Form("")
) -> Response:
    _admin(request)
    check_csrf(request, csrf_token)
    if show not in _CONFUSION_CHOICES:
        raise InvalidInputError(f"show: expected auto, show or hide, found {show[:20]!r}")
    state = state_of(request)
    set_show_confusion(state.factory, name, show=_CONFUSION_CHOICES[show])
    state.leaderboards.invalidate(name)
    return RedirectResponse("/admin", status_code=303)
