"""Submissions: the submit page, "my submissions", a submission's status / method page.

A submission's page is public once published (its method card, overall scores and the
confusion-matrix heatmap); before that only its owner (and admins) see it, errors
included. Per-scan scores are shown nowhere.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Form, Request
from fastapi.responses import RedirectResponse, Response
from pydantic import BaseModel

from semantic3d.server.challenges import list_challenges
from semantic3d.server.heatmap import confusion_svg
from semantic3d.server.models import JOB_QUEUED, JOB_RUNNING
from semantic3d.server.submissions import (
    result_of,
    set_published,
    submission_dict,
    user_submissions,
    visible_submission,
)
from semantic3d.server.web import (
    api_user,
    check_csrf,
    optional_user,
    render,
    session_user,
    state_of,
)

router = APIRouter()


class PublishRequest(BaseModel):
    """Show (``true``) or hide (``false``) an evaluated submission on its leaderboard."""

    published: bool


@router.get("/api/submissions", tags=["submissions"])
def api_my_submissions(request: Request) -> dict[str, Any]:
    """The caller's submissions, newest first."""
    user = api_user(request)
    rows = user_submissions(state_of(request).factory, user.id)
    return {"submissions": [submission_dict(row, owner=True) for row in rows]}


@router.get("/api/submissions/{submission_id}", tags=["submissions"])
def api_submission(request: Request, submission_id: int) -> dict[str, Any]:
    """One submission: status and progress; scores once evaluated (if published or yours)."""
    user = optional_user(request)
    with state_of(request).factory() as session:
        row = visible_submission(
            session,
            submission_id,
            viewer_id=user.id if user else None,
            viewer_is_admin=bool(user and user.is_admin),
        )
        return submission_dict(row, owner=user is not None and user.id == row.user_id)


@router.post("/api/submissions/{submission_id}/publish", tags=["submissions"])
def api_publish(request: Request, submission_id: int, body: PublishRequest) -> dict[str, Any]:
    """Publish or withdraw one of your evaluated submissions."""
    user = api_user(request)
    state = state_of(request)
    set_published(
        state.factory, user_id=user.id, submission_id=submission_id, published=body.published
    )
    state.leaderboards.invalidate(None)
    with state.factory() as session:
        row = visible_submission(session, submission_id, viewer_id=user.id)
        return submission_dict(row, owner=True)


@router.get("/submit", include_in_schema=False)
def submit_page(request: Request, challenge: str = "") -> Response:
    user = request.state.user = session_user(request)
    if user is None:
        return RedirectResponse("/login?next=/submit", status_code=303)
    challenges = [row for row in list_challenges(state_of(request).factory) if row.is_open]
    return render(
        request,
        "submit.html",
        {
            "challenges": challenges,
            "selected": challenge,
            "max_upload_bytes": state_of(request).settings.max_upload_bytes,
        },
    )


@router.get("/submissions", include_in_schema=False)
def my_submissions_page(request: Request) -> Response:
    user = request.state.user = session_user(request)
    if user is None:
        return RedirectResponse("/login?next=/submissions", status_code=303)
    rows = user_submissions(state_of(request).factory, user.id)
    return render(request, "submissions.html", {"submissions": rows})


@router.get("/submissions/{submission_id}", include_in_schema=False)
def submission_page(request: Request, submission_id: int) -> Response:
    user = request.state.user = session_user(request)
    with state_of(request).factory() as session:
        row = visible_submission(
            session,
            submission_id,
            viewer_id=user.id if user else None,
            viewer_is_admin=bool(user and user.is_admin),
        )
        job, challenge = row.job, row.challenge
        owner = user is not None and user.id == row.user_id
        result = result_of(row)
        heatmap = (
            confusion_svg(result.confusion, title=f"{row.method_name} on {challenge.name}")
            if result is not None
            else None
        )
        return render(
            request,
            "submission.html",
            {
                "submission": row,
                "job": job,
                "challenge": challenge,
                "owner": owner,
                "heatmap": heatmap,
                "iou": submission_dict(row, owner=owner)["scores"],
                "pending": job.status in (JOB_QUEUED, JOB_RUNNING),
            },
        )


@router.post("/submissions/{submission_id}/publish", include_in_schema=False)
def publish_form(
    request: Request, submission_id: int, published: str = Form("1"), csrf_token: str = Form("")
) -> Response:
    user = session_user(request)
    if user is None:
        return RedirectResponse(f"/login?next=/submissions/{submission_id}", status_code=303)
    check_csrf(request, csrf_token)
    state = state_of(request)
    set_published(
        state.factory, user_id=user.id, submission_id=submission_id, published=published == "1"
    )
    state.leaderboards.invalidate(None)
    return RedirectResponse(f"/submissions/{submission_id}", status_code=303)
