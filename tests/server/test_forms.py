"""Every state-changing route: CSRF for cookie sessions, the admin role, cookie flags.

The routes are enumerated from the app, so a form or API route added later without a
CSRF check (or without a case here) fails these tests.
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

from fastapi.routing import APIRoute
from sqlalchemy import select

from semantic3d.server import routers
from semantic3d.server.models import ApiToken, ChallengeRecord, Job, Submission, User
from semantic3d.server.services.upload_files import received_bytes

from .conftest import (
    PASSWORD,
    Harness,
    build_harness,
    form_csrf,
    ground_truth_arrays,
    make_settings,
    noisy_predictions,
    submission_zip,
    web_login,
)

_UNSAFE = {"POST", "PUT", "PATCH", "DELETE"}
# Forms that work without a login (and so need no account to forge against).
_ANONYMOUS_FORMS = {"/login", "/register"}


def _all_routes(harness: Harness) -> list[APIRoute]:
    """The app's own routes and those of every module in ``semantic3d.server.routers``."""
    found = [route for route in harness.client.app.routes if isinstance(route, APIRoute)]
    for module in pkgutil.iter_modules(routers.__path__):
        router = importlib.import_module(f"{routers.__name__}.{module.name}").router
        found.extend(route for route in router.routes if isinstance(route, APIRoute))
    return found


def _unsafe_routes(harness: Harness, *, api: bool) -> list[tuple[str, str]]:
    routes = []
    for route in _all_routes(harness):
        if route.path.startswith("/api/") != api:
            continue
        routes.extend((method, route.path) for method in sorted(route.methods & _UNSAFE))
    assert routes, "no state-changing routes found"
    return routes


def _evaluated_submission(harness: Harness, token: str) -> int:
    response = harness.submit(token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)))
    assert response.status_code == 201, response.text
    assert harness.work() is True
    return int(response.json()["id"])


def _snapshot(harness: Harness) -> tuple[object, ...]:
    """The state a forged request could change: accounts' tokens, submissions, challenges."""
    with harness.state.factory() as session:
        tokens = tuple(session.execute(select(ApiToken.id, ApiToken.revoked_at)).all())
        submissions = tuple(session.execute(select(Submission.id, Submission.published)).all())
        jobs = tuple(session.execute(select(Job.id, Job.status, Job.attempts)).all())
        challenges = tuple(
            session.execute(select(ChallengeRecord.name, ChallengeRecord.is_open)).all()
        )
        users = tuple(session.execute(select(User.id, User.is_admin)).all())
    return tokens, submissions, jobs, challenges, users


def test_every_form_refuses_a_missing_or_forged_csrf_token(harness: Harness) -> None:
    token = harness.user_token("root", admin=True)
    submission_id = _evaluated_submission(harness, token)
    with harness.state.factory() as session:
        token_id = session.scalars(select(ApiToken.id)).one()
    values = {
        "{token_id}": str(token_id),
        "{submission_id}": str(submission_id),
        "{name}": "toy",
        "{upload_id}": "0" * 32,
    }
    fields = {
        "/register": {"username": "mallory", "password": PASSWORD, "password_again": PASSWORD},
        "/login": {"username": "root", "password": PASSWORD},
        "/account/tokens": {"name": "forged"},
        "/admin/challenges/{name}/open": {"is_open": "0"},
        "/submissions/{submission_id}/publish": {"published": "1"},
    }
    assert web_login(harness.client, "root", PASSWORD).status_code == 303
    before = _snapshot(harness)
    forms = _unsafe_routes(harness, api=False)
    assert {"/logout", "/account/tokens/{token_id}/revoke", "/admin/challenges/{name}/open"} <= {
        path for _, path in forms
    }
    for method, path in forms:
        url = path
        for placeholder, value in values.items():
            url = url.replace(placeholder, value)
        assert "{" not in url, f"no test value for {path}: add one here"
        for forged in ({}, {"csrf_token": "forged"}, {"csrf_token": ""}):
            data = fields.get(path, {}) | forged
            response = harness.client.request(method, url, data=data, follow_redirects=False)
            assert response.status_code == 403, (method, path, forged, response.status_code)
            assert "CSRF" in response.text, (method, path)
        if path not in _ANONYMOUS_FORMS:
            # The forms behind a login answer 403 for a forged token, not a login redirect.
            assert harness.client.get("/account").status_code == 200, "logged out by a forgery"
    assert _snapshot(harness) == before
    # The same requests with the session's token do go through (the check is the CSRF).
    csrf = form_csrf(harness.client.get("/account").text)
    response = harness.client.post(
        "/admin/challenges/toy/open", data={"is_open": "0", "csrf_token": csrf}
    )
    assert response.status_code == 200 and _snapshot(harness) != before


def test_every_unsafe_api_route_needs_the_csrf_header_when_called_by_cookie(
    harness: Harness,
) -> None:
    token = harness.user_token("alice")
    submission_id = _evaluated_submission(harness, token)
    upload_id = harness.upload(token, b"x" * 10)
    values = {"{upload_id}": upload_id, "{submission_id}": str(submission_id)}
    bodies: dict[str, dict[str, object]] = {
        "/api/uploads": {"challenge": "toy", "size_bytes": 10},
        "/api/uploads/{upload_id}/finalize": {"method": {"name": "forged"}},
        "/api/submissions/{submission_id}/publish": {"published": True},
    }
    web_login(harness.client, "alice", PASSWORD)
    before = _snapshot(harness)
    received = harness.client.get(
        f"/api/uploads/{upload_id}", headers={"Authorization": f"Bearer {token}"}
    ).json()["received_bytes"]
    for method, path in _unsafe_routes(harness, api=True):
        url = path
        for placeholder, value in values.items():
            url = url.replace(placeholder, value)
        assert "{" not in url, f"no test value for {path}: add one here"
        for headers in ({}, {"X-CSRF-Token": "forged"}):
            response = harness.client.request(
                method,
                url,
                json=bodies.get(path),
                params={"offset": received} if method == "PUT" else None,
                headers=headers,
            )
            assert response.status_code == 403, (method, path, headers, response.text)
    assert _snapshot(harness) == before
    assert received_bytes(harness.settings, upload_id) == received == 10


def test_admin_routes_refuse_other_accounts_and_visitors(harness: Harness) -> None:
    token = harness.user_token("alice")
    submission_id = _evaluated_submission(harness, token)
    admin_posts = [path for _, path in _unsafe_routes(harness, api=False) if "/admin" in path]
    assert len(admin_posts) >= 2
    before = _snapshot(harness)
    for logged_in in (False, True):
        if logged_in:
            web_login(harness.client, "alice", PASSWORD)
        csrf = form_csrf(harness.client.get("/login").text)
        assert harness.client.get("/admin").status_code == 403
        for path in admin_posts:
            url = path.replace("{submission_id}", str(submission_id)).replace("{name}", "toy")
            response = harness.client.post(url, data={"is_open": "0", "csrf_token": csrf})
            assert response.status_code == 403, (path, logged_in)
            assert "administrators" in response.text
    assert _snapshot(harness) == before


def test_session_cookie_flags(tmp_path: Path, ground_truth_dir: Path) -> None:
    harnesses = build_harness(
        make_settings(tmp_path / "data", cookie_secure=True, session_max_age_s=3600),
        ground_truth_dir,
    )
    harness = next(harnesses)
    try:
        cookie = harness.client.get("/login").headers["set-cookie"].lower()
        assert cookie.startswith("semantic3d_session=")
        for flag in ("httponly", "secure", "samesite=lax", "max-age=3600", "path=/"):
            assert flag in cookie, flag
    finally:
        harnesses.close()
