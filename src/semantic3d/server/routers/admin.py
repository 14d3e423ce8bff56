"""The admin page: queue state, every submission, requeue, open/close challenges.

Ground truth is installed from the command line (``semantic3d admin add-challenge``), never
uploaded through the web: the page says which challenges still lack it.
"""

from __future__ import annotations

from fastapi import APIRouter, Form, Request
from fastapi.responses import RedirectResponse, Response
from sqlalchemy import select

from semantic3d.server.deps import AdminUser, State
from semantic3d.server.errors import InvalidInputError
from semantic3d.server.models import Submission
from semantic3d.server.services.challenges import (
    CONFUSION_MIN_SCANS,
    install_hint,
    list_challenges,
    set_challenge_open,
    set_show_confusion,
)
from semantic3d.server.services.queue import queue_counts, requeue
from semantic3d.server.web import check_csrf, render

router = APIRouter(prefix="/admin", include_in_schema=False)


@router.get("")
def admin_page(request: Request, admin: AdminUser, state: State) -> Response:
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
def admin_requeue(
    request: Request,
    submission_id: int,
    admin: AdminUser,
    state: State,
    csrf_token: str = Form(""),
) -> Response:
    check_csrf(request, csrf_token)
    requeue(state.factory, submission_id)
    return RedirectResponse("/admin", status_code=303)


@router.post("/challenges/{name}/open")
def admin_open(
    request: Request,
    name: str,
    admin: AdminUser,
    state: State,
    is_open: str = Form("1"),
    csrf_token: str = Form(""),
) -> Response:
    check_csrf(request, csrf_token)
    set_challenge_open(state.factory, name, is_open=is_open == "1")
    state.leaderboards.invalidate(name)
    return RedirectResponse("/admin", status_code=303)


_CONFUSION_CHOICES = {"auto": None, "show": True, "hide": False}


@router.post("/challenges/{name}/confusion")
def admin_confusion(
    request: Request,
    name: str,
    admin: AdminUser,
    state: State,
    show: str = Form("auto"),
    csrf_token: str = Form(""),
) -> Response:
    check_csrf(request, csrf_token)
    if show not in _CONFUSION_CHOICES:
        raise InvalidInputError(f"show: expected auto, show or hide, found {show[:20]!r}")
    set_show_confusion(state.factory, name, show=_CONFUSION_CHOICES[show])
    state.leaderboards.invalidate(name)
    return RedirectResponse("/admin", status_code=303)
