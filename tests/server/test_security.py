"""Hidden ground truth stays hidden; logins are throttled; CSRF, redirects and headers."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from .conftest import (
    PASSWORD,
    Harness,
    build_harness,
    form_csrf,
    make_settings,
    web_login,
    web_register,
)

GT_PROBES = [
    "/static/../ground-truth/toy/scan_a.labels",
    "/static/%2e%2e/ground-truth/toy/scan_a.labels",
    "/static/..%2fground-truth/toy/scan_a.labels",
    "/static/%2e%2e%2f%2e%2e%2fsemantic3d.sqlite3",
    "/ground-truth/toy/scan_a.labels",
    "/data/ground-truth/toy/scan_a.labels",
    "/semantic3d-data/ground-truth/toy/scan_a.labels",
    "/static//etc/passwd",
    "/submissions/../ground-truth/toy/scan_a.labels",
    "/api/challenges/toy/scan_a.labels",
    "/api/challenges/..%2f..%2fground-truth",
    "/secret_key",
    "/static/secret_key",
]


def test_hidden_ground_truth_is_unreachable(harness: Harness) -> None:
    gt_file = harness.settings.ground_truth_dir / "toy" / "scan_a.labels"
    secret = gt_file.read_bytes()
    assert len(secret) > 1000
    for probe in GT_PROBES:
        response = harness.client.get(probe)
        assert response.status_code in (400, 404, 405), probe
        assert secret[:200] not in response.content, probe
    for url in ("/api/challenges", "/api/challenges/toy", "/", "/challenges/toy"):
        text = harness.client.get(url).text
        assert str(harness.settings.data_dir) not in text, url
        assert "ground-truth" not in text, url


def test_ground_truth_folder_is_private_to_the_server_user(harness: Harness) -> None:
    mode = harness.settings.ground_truth_dir.stat().st_mode & 0o777
    assert mode == 0o700


@pytest.fixture
def throttled(tmp_path: Path, ground_truth_dir: Path) -> Iterator[Harness]:
    settings = make_settings(
        tmp_path / "data",
        login_max_failures=3,
        login_max_failures_per_ip=50,
        login_max_failures_per_account=6,
        login_window_s=600,
    )
    yield from build_harness(settings, ground_truth_dir)


def test_brute_force_login_is_throttled(throttled: Harness) -> None:
    throttled.user_token("alice")
    client = throttled.client
    for _ in range(3):
        assert web_login(client, "alice", "wrong password").status_code == 401
    # Now even the right password is refused until the window passes.
    blocked = web_login(client, "alice", PASSWORD)
    assert blocked.status_code == 429
    assert "too many login attempts" in blocked.text
    assert 0 < int(blocked.headers["Retry-After"]) <= 600
    # Other accounts can still log in.
    throttled.user_token("bob")
    assert web_login(client, "bob", PASSWORD).status_code == 303


def _guess(harness: Harness, password: str, address: str) -> str:
    from semantic3d.server.errors import AuthenticationError, ThrottledError
    from semantic3d.server.services.accounts import authenticate

    try:
        authenticate(harness.state.factory, harness.settings, "alice", password, address=address)
    except AuthenticationError:
        return "wrong"
    except ThrottledError as exc:
        return f"throttled {exc.retry_after_s}"
    return "in"


def test_a_stranger_cannot_lock_the_owner_out(throttled: Harness) -> None:
    throttled.user_token("alice")
    outcomes = [_guess(throttled, "wrong password", "203.0.113.9") for _ in range(5)]
    assert outcomes[:3] == ["wrong"] * 3
    assert all(outcome.startswith("throttled") for outcome in outcomes[3:])
    # The owner, from elsewhere, still gets in.
    assert _guess(throttled, PASSWORD, "198.51.100.7") == "in"


def test_distributed_guessing_is_capped_per_account(throttled: Harness) -> None:
    throttled.user_token("alice")
    outcomes = [_guess(throttled, "wrong password", f"10.0.0.{i}") for i in range(10)]
    assert outcomes[:6] == ["wrong"] * 6  # at most login_max_failures_per_account checked
    assert all(outcome.startswith("throttled") for outcome in outcomes[6:])
    assert _guess(throttled, PASSWORD, "10.0.1.1").startswith("throttled")


def test_hammering_on_does_not_prolong_the_lock(throttled: Harness) -> None:
    from sqlalchemy import func, select

    from semantic3d.server.models import LoginFailure

    throttled.user_token("alice")
    for _ in range(3):
        assert _guess(throttled, "wrong password", "203.0.113.9") == "wrong"
    retries = [_guess(throttled, "wrong password", "203.0.113.9") for _ in range(20)]
    assert all(outcome.startswith("throttled") for outcome in retries)
    # Only the three checked guesses are on record: the lock ends when Retry-After says.
    with throttled.state.factory() as session:
        assert session.scalar(select(func.count()).select_from(LoginFailure)) == 3
    assert max(int(outcome.split()[1]) for outcome in retries) <= 600


def test_a_successful_login_clears_the_failures(throttled: Harness) -> None:
    throttled.user_token("alice")
    for _ in range(2):
        web_login(throttled.client, "alice", "wrong password")
    assert web_login(throttled.client, "alice", PASSWORD).status_code == 303
    for _ in range(2):
        assert web_login(throttled.client, "alice", "wrong password").status_code == 401


def test_concurrent_guesses_get_at_most_the_allowed_checks(throttled: Harness) -> None:
    from semantic3d.server.errors import AuthenticationError, ThrottledError
    from semantic3d.server.services.accounts import authenticate

    throttled.user_token("alice")
    outcomes: list[str] = []
    barrier = threading.Barrier(8)

    def guess(index: int) -> None:
        barrier.wait()
        try:
            authenticate(
                throttled.state.factory,
                throttled.settings,
                "alice",
                f"guess {index}",
                address="10.0.0.1",
            )
            outcomes.append("in")
        except AuthenticationError:
            outcomes.append("wrong")
        except ThrottledError:
            outcomes.append("throttled")

    threads = [threading.Thread(target=guess, args=(i,)) for i in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert outcomes.count("wrong") <= 3
    assert outcomes.count("throttled") >= 5


def test_unknown_user_is_indistinguishable_from_a_wrong_password(harness: Harness) -> None:
    harness.user_token("alice")
    wrong = web_login(harness.client, "alice", "nope nope nope")
    unknown = web_login(harness.client, "nobody", "nope nope nope")
    assert wrong.status_code == unknown.status_code == 401
    assert (
        "wrong username or password" in wrong.text and "wrong username or password" in unknown.text
    )


def test_forms_need_the_csrf_token(harness: Harness) -> None:
    harness.user_token("alice")
    client = harness.client
    client.get("/login")
    response = client.post(
        "/login", data={"username": "alice", "password": PASSWORD}, follow_redirects=False
    )
    assert response.status_code == 403 and "CSRF" in response.text
    assert web_login(client, "alice", PASSWORD).status_code == 303
    # Logged in by cookie: API writes need the CSRF header too.
    body = {"challenge": "toy", "size_bytes": 10}
    assert client.post("/api/uploads", json=body).status_code == 403
    csrf = form_csrf(client.get("/account").text)
    assert client.post("/api/uploads", json=body, headers={"X-CSRF-Token": csrf}).status_code == 201
    assert client.post("/logout", data={"csrf_token": "forged"}).status_code == 403


def test_login_redirects_only_to_local_paths(harness: Harness) -> None:
    harness.user_token("alice")
    page = harness.client.get("/login", params={"next": "https://evil.example/"})
    assert 'value="/"' in page.text and "evil.example" not in page.text
    response = harness.client.post(
        "/login",
        data={
            "username": "alice",
            "password": PASSWORD,
            "next": "//evil.example/",
            "csrf_token": form_csrf(page.text),
        },
        follow_redirects=False,
    )
    assert response.status_code == 303 and response.headers["location"] == "/"


def test_security_headers(harness: Harness) -> None:
    response = harness.client.get("/")
    assert response.headers["x-frame-options"] == "DENY"
    assert response.headers["x-content-type-options"] == "nosniff"
    assert "script-src 'self'" in response.headers["content-security-policy"]
    assert "set-cookie" not in response.headers  # no session for anonymous reading
    cookie = harness.client.get("/login").headers.get("set-cookie", "")
    assert "httponly" in cookie.lower() and "samesite=lax" in cookie.lower()


def test_tokens_are_stored_hashed_and_can_be_revoked(harness: Harness) -> None:
    from sqlalchemy import select

    from semantic3d.server.models import ApiToken

    token = harness.user_token("alice")
    with harness.state.factory() as session:
        stored = session.scalars(select(ApiToken)).one()
    assert token not in (stored.token_hash, stored.prefix) and stored.token_hash != token
    assert len(stored.token_hash) == 64
    headers = {"Authorization": f"Bearer {token}"}
    assert harness.client.get("/api/me", headers=headers).status_code == 200
    web_login(harness.client, "alice", PASSWORD)
    account = harness.client.get("/account")
    assert token not in account.text  # shown once, at creation only
    harness.client.post(
        f"/account/tokens/{stored.id}/revoke", data={"csrf_token": form_csrf(account.text)}
    )
    assert harness.client.get("/api/me", headers=headers).status_code == 401


def test_the_page_showing_a_new_token_is_never_cached(harness: Harness) -> None:
    assert web_register(harness.client, "alice").status_code == 303
    account = harness.client.get("/account")
    assert account.headers["cache-control"] == "no-store"
    created = harness.client.post(
        "/account/tokens", data={"name": "laptop", "csrf_token": form_csrf(account.text)}
    )
    assert created.status_code == 200 and "s3d_" in created.text
    assert created.headers["cache-control"] == "no-store"


def test_no_route_serves_files_from_the_data_dir(harness: Harness) -> None:
    from starlette.routing import Mount

    from semantic3d.server.web import STATIC_DIR

    app = harness.client.app
    mounts = [route for route in app.routes if isinstance(route, Mount)]
    assert [m.path for m in mounts] == ["/static"]
    static_root = Path(mounts[0].app.directory).resolve()
    assert static_root == STATIC_DIR.resolve()
    assert not static_root.is_relative_to(harness.settings.data_dir)
    assert not harness.settings.data_dir.is_relative_to(static_root)


def test_large_form_and_json_bodies_are_refused_unread(harness: Harness) -> None:
    from semantic3d.server.app import MAX_BODY_BYTES

    token = harness.user_token("alice")
    big = "x" * (MAX_BODY_BYTES + 1)
    page = harness.client.post("/login", data={"username": "alice", "password": big})
    assert page.status_code == 413 and "at most" in page.text
    upload_id = "0" * 32
    api = harness.client.post(
        f"/api/uploads/{upload_id}/finalize",
        json={"method": {"name": "m", "description": big}},
        headers={"Authorization": f"Bearer {token}"},
    )
    assert api.status_code == 413 and "/api/uploads" in api.json()["error"]

    def chunks(n_blocks: int) -> Iterator[bytes]:
        yield b'{"challenge": "toy", "filename": "'
        for _ in range(n_blocks):
            yield b"z" * (256 << 10)
        yield b'", "size_bytes": 10}'

    headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    # Without Content-Length (chunked): counted as it arrives.
    chunked = harness.client.post("/api/uploads", content=chunks(5), headers=headers)
    assert chunked.status_code == 413 and "at most" in chunked.json()["error"]
    form = harness.client.post(
        "/login",
        content=chunks(5),
        headers={"Content-Type": "application/x-www-form-urlencoded"},
    )
    assert form.status_code == 413 and "text/html" in form.headers["content-type"]
    small = harness.client.post("/api/uploads", content=chunks(0), headers=headers)
    assert small.status_code == 201, small.text
    # Ordinary requests and upload chunks (which stream to disk) are not affected.
    assert web_login(harness.client, "alice", PASSWORD).status_code == 303
    assert harness.upload(token, b"y" * (MAX_BODY_BYTES + 10), chunk=MAX_BODY_BYTES * 2)


def _csp(response) -> dict[str, list[str]]:  # type: ignore[no-untyped-def]
    directives = {}
    for part in response.headers["content-security-policy"].split(";"):
        name, *values = part.split()
        directives[name] = values
    return directives


def test_api_docs_page_may_load_what_it_needs_and_only_it(harness: Harness) -> None:
    import re

    page = harness.client.get("/api/docs")
    assert page.status_code == 200
    policy = _csp(page)
    scripts = re.findall(r'<script src="([^"]+)"', page.text)
    styles = re.findall(r'<link rel="stylesheet" href="([^"]+)"', page.text)
    assert scripts and styles
    # Served from the package: same origin only, no inline script, no CDN.
    assert all(url.startswith("/static/") for url in scripts + styles), (scripts, styles)
    assert "<script>" not in page.text
    assert policy["script-src"] == ["'self'"]
    assert not [value for values in policy.values() for value in values if "http" in value]
    # Every other page keeps the strict policy.
    for url in ("/", "/login", "/api/challenges", "/api/openapi.json"):
        strict = _csp(harness.client.get(url))
        assert strict["script-src"] == ["'self'"] and strict["style-src"] == ["'self'"], url


def test_logging_out_ends_the_session_even_for_a_copied_cookie(harness: Harness) -> None:
    harness.user_token("alice")
    client = harness.client
    assert web_login(client, "alice", PASSWORD).status_code == 303
    stolen = client.cookies.get("semantic3d_session")
    assert stolen and client.get("/account").status_code == 200
    logout = client.post("/logout", data={"csrf_token": form_csrf(client.get("/account").text)})
    assert logout.status_code == 200  # redirected home
    client.cookies.clear()
    client.cookies.set("semantic3d_session", stolen)
    replay = client.get("/account", follow_redirects=False)
    assert replay.status_code == 303 and replay.headers["location"].startswith("/login")
    # Logging in again works and gives a working session.
    client.cookies.clear()
    assert web_login(client, "alice", PASSWORD).status_code == 303
    assert "Account alice" in client.get("/account").text
