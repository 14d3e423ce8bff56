"""Submissions: the submit page, "my submissions", a submission's status / method page.

A submission's page is public once published (its method card, overall scores and the
confusion-matrix heatmap); before that only its owner (and admins) see it, errors
included. Per-scan scores are shown nowhere.
"""

from __future__ import annotations

from enum import Enum

from fastapi import APIRouter, Form, Request
from fastapi.responses import RedirectResponse, Response
from sqlalchemy import select

from semantic3d.server.deps import CurrentUser, DbSession, OptionalUser, PageUser, State
from semantic3d.server.heatmap import confusion_svg
from semantic3d.server.models import JOB_QUEUED, JOB_RUNNING, Submission, utc_now
from semantic3d.server.schemas import (
    PublishRequest,
    SubmissionInfo,
    SubmissionList,
    error_responses,
)
from semantic3d.server.services.challenges import (
    CONFUSION_MIN_SCANS,
    accepts_submissions,
    list_challenges,
    shows_confusion,
    submission_status,
)
from semantic3d.server.services.scores import result_of
from semantic3d.server.services.submissions import (
    next_submission_at,
    set_published,
    submission_info,
    user_submissions,
    visible_submission,
)
from semantic3d.server.web import check_csrf, render

router = APIRouter()


_TAGS: list[str | Enum] = ["submissions"]
_ERRORS = error_responses(400, 401, 403, 404, 422, 503, 507)
# ``response_model_exclude_unset``: owner-only fields are left out (not sent as null) for
# everyone else.


@router.get(
    "/api/submissions",
    response_model=SubmissionList,
    response_model_exclude_unset=True,
    tags=_TAGS,
    responses=_ERRORS,
)
def api_my_submissions(user: CurrentUser, state: State) -> SubmissionList:
    """The caller's submissions, newest first."""
    rows = user_submissions(state.factory, user.id)
    return SubmissionList(
        submissions=[
            submission_info(row, owner=True, confusion=_sees_confusion(row, user.is_admin))
            for row in rows
        ]
    )


@router.get(
    "/api/submissions/{submission_id}",
    response_model=SubmissionInfo,
    response_model_exclude_unset=True,
    tags=_TAGS,
    responses=_ERRORS,
)
def api_submission(submission_id: int, user: OptionalUser, db: DbSession) -> SubmissionInfo:
    """One submission: status and progress; scores once evaluated (if published or yours)."""
    row = visible_submission(
        db,
        submission_id,
        viewer_id=user.id if user else None,
        viewer_is_admin=bool(user and user.is_admin),
    )
    return submission_info(
        row,
        owner=user is not None and user.id == row.user_id,
        confusion=_sees_confusion(row, user is not None and user.is_admin),
    )


@router.post(
    "/api/submissions/{submission_id}/publish",
    response_model=SubmissionInfo,
    response_model_exclude_unset=True,
    tags=_TAGS,
    responses=_ERRORS,
)
def api_publish(
    submission_id: int, body: PublishRequest, user: CurrentUser, state: State, db: DbSession
) -> SubmissionInfo:
    """Publish or withdraw one of your evaluated submissions."""
    set_published(
        state.factory, user_id=user.id, submission_id=submission_id, published=body.published
    )
    state.leaderboards.invalidate(None)
    row = visible_submission(db, submission_id, viewer_id=user.id)
    return submission_info(row, owner=True, confusion=_sees_confusion(row, user.is_admin))


def _sees_confusion(row: Submission, is_admin: bool) -> bool:
    """Confusion matrices follow the challenge's policy; administrators always see them."""
    return is_admin or shows_confusion(row.challenge)


@router.get("/submit", include_in_schema=False)
def submit_page(request: Request, user: PageUser, state: State, challenge: str = "") -> Response:
    if user is None:
        return RedirectResponse("/login?next=/submit", status_code=303)
    rows = list_challenges(state.factory)
    challenges = [row for row in rows if accepts_submissions(row)]
    now = utc_now()
    cooldowns = []
    with state.factory() as session:
        for row in challenges:
            next_at = next_submission_at(
                session, state.settings, user_id=user.id, challenge_id=row.id
            )
            wait_s = (next_at - now).total_seconds() if next_at and next_at > now else None
            cooldowns.append({"challenge": row, "next_at": next_at, "wait_s": wait_s})
        in_flight = session.scalar(
            select(Submission.id).where(Submission.user_id == user.id, Submission.in_flight)
        )
    return render(
        request,
        "submit.html",
        {
            "challenges": challenges,
            "not_open": [row for row in rows if not accepts_submissions(row)],
            "status_of": submission_status,
            "selected": challenge,
            "hint_challenge": challenge
            if challenge in {row.name for row in challenges}
            else (challenges[0].name if challenges else "NAME"),
            "max_upload_bytes": state.settings.max_upload_bytes,
            "cooldown_h": state.settings.submission_cooldown_h,
            "cooldowns": cooldowns,
            "in_flight": in_flight,
            "base_url": str(request.base_url).rstrip("/"),
        },
    )


@router.get("/submissions", include_in_schema=False)
def my_submissions_page(request: Request, user: PageUser, state: State) -> Response:
    if user is None:
        return RedirectResponse("/login?next=/submissions", status_code=303)
    rows = user_submissions(state.factory, user.id)
    return render(request, "submissions.html", {"submissions": rows})


@router.get("/submissions/{submission_id}", include_in_schema=False)
def submission_page(
    request: Request, submission_id: int, user: PageUser, db: DbSession
) -> Response:
    row = visible_submission(
        db,
        submission_id,
        viewer_id=user.id if user else None,
        viewer_is_admin=bool(user and user.is_admin),
    )
    job, challenge = row.job, row.challenge
    owner = user is not None and user.id == row.user_id
    result = result_of(row)
    show_matrix = _sees_confusion(row, bool(user and user.is_admin))
    heatmap = (
        confusion_svg(result.confusion, title=f"{row.method_name} on {challenge.name}")
        if result is not None and show_matrix
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
            "iou": submission_info(row, owner=owner, confusion=False).scores,
            "pending": job.status in (JOB_QUEUED, JOB_RUNNING),
            "confusion_hidden": result is not None and not show_matrix,
            "confusion_min_scans": CONFUSION_MIN_SCANS,
        },
    )


@router.post("/submissions/{submission_id}/publish", include_in_schema=False)
def publish_form(
    request: Request,
    submission_id: int,
    user: PageUser,
    state: State,
    published: str = Form("1"),
    csrf_token: str = Form(""),
) -> Response:
    if user is None:
        return RedirectResponse(f"/login?next=/submissions/{submission_id}", status_code=303)
    check_csrf(request, csrf_token)
    set_published(
        state.factory, user_id=user.id, submission_id=submission_id, published=published == "1"
    )
    state.leaderboards.invalidate(None)
    return RedirectResponse(f"/submissions/{submission_id}", status_code=303)
