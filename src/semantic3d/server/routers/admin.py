"""The admin page: queue state, every submission, requeue, open/close challenges."""

from __future__ import annotations

from fastapi import APIRouter, Form, Request
from fastapi.responses import RedirectResponse, Response
from sqlalchemy import select

from semantic3d.server.challenges import list_challenges, set_challenge_open
from semantic3d.server.errors import ForbiddenError
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
    set_challenge_open(state_of(request).factory, name, is_open=is_open == "1")
    return RedirectResponse("/admin", status_code=303)
