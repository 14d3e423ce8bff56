"""Server-rendered pages: registration, account tokens, my submissions, status, admin."""

from __future__ import annotations

import re

from .conftest import (
    PASSWORD,
    Harness,
    form_csrf,
    ground_truth_arrays,
    noisy_predictions,
    submission_zip,
    web_login,
    web_register,
)


def test_register_then_create_a_token_shown_once(harness: Harness) -> None:
    client = harness.client
    response = web_register(client, "Carol")
    assert response.status_code == 303 and response.headers["location"] == "/account"
    account = client.get("/account")
    assert "Account carol" in account.text
    created = client.post(
        "/account/tokens", data={"name": "laptop", "csrf_token": form_csrf(account.text)}
    )
    token = re.search(r'<pre id="new-token">(s3d_[^<]+)</pre>', created.text).group(1)
    assert client.get("/api/me", headers={"Authorization": f"Bearer {token}"}).json() == {
        "username": "carol",
        "is_admin": False,
    }
    assert token not in client.get("/account").text


def test_registration_errors_are_shown_on_the_form(harness: Harness) -> None:
    assert web_register(harness.client, "dave").status_code == 303
    harness.client.cookies.clear()
    taken = web_register(harness.client, "DAVE")
    assert taken.status_code == 400 and "already taken" in taken.text
    short = web_register(harness.client, "erin", password="short")
    assert short.status_code == 400 and "password: expected 8" in short.text


def test_registration_can_be_closed(tmp_path, ground_truth_dir) -> None:
    from .conftest import build_harness, make_settings

    harness_iter = build_harness(
        make_settings(tmp_path / "data", registration_open=False), ground_truth_dir
    )
    harness = next(harness_iter)
    try:
        assert "Registration is closed" in harness.client.get("/register").text
        page = harness.client.get("/login")
        response = harness.client.post(
            "/register",
            data={
                "username": "frank",
                "password": PASSWORD,
                "password_again": PASSWORD,
                "csrf_token": form_csrf(page.text),
            },
        )
        assert response.status_code == 403
    finally:
        harness_iter.close()


def test_pages_that_need_a_login_redirect_to_it(harness: Harness) -> None:
    for path in ("/submit", "/submissions", "/account"):
        response = harness.client.get(path, follow_redirects=False)
        assert response.status_code == 303
        assert response.headers["location"] == f"/login?next={path}"


def test_submission_pages_follow_the_job(harness: Harness) -> None:
    token = harness.user_token("alice")
    web_login(harness.client, "alice", PASSWORD)
    submit_page = harness.client.get("/submit")
    assert 'id="submit-form"' in submit_page.text and "upload.js" in submit_page.text
    submission_id = harness.submit(
        token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)), "Forest"
    ).json()["id"]
    queued = harness.client.get(f"/submissions/{submission_id}")
    assert 'http-equiv="refresh"' in queued.text and "queued" in queued.text
    assert "Forest" in harness.client.get("/submissions").text
    harness.work()
    done = harness.client.get(f"/submissions/{submission_id}")
    assert 'http-equiv="refresh"' not in done.text
    assert 'id="publish"' in done.text and "<svg" in done.text
    harness.client.post(
        f"/submissions/{submission_id}/publish",
        data={"published": "1", "csrf_token": form_csrf(done.text)},
    )
    board = harness.client.get("/challenges/toy")
    assert f'href="/submissions/{submission_id}"' in board.text and "Forest" in board.text
    index = harness.client.get("/")
    assert "Toy challenge" in index.text


def test_admin_page_is_for_admins_only(harness: Harness) -> None:
    harness.user_token("alice")
    web_login(harness.client, "alice", PASSWORD)
    assert harness.client.get("/admin").status_code == 403
    harness.client.cookies.clear()
    harness.user_token("root", admin=True)
    web_login(harness.client, "root", PASSWORD)
    page = harness.client.get("/admin")
    assert page.status_code == 200 and "Queue" in page.text


def test_admin_can_requeue_and_close_a_challenge(harness: Harness) -> None:
    token = harness.user_token("alice")
    submission_id = harness.submit(
        token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    ).json()["id"]
    harness.work()
    harness.user_token("root", admin=True)
    web_login(harness.client, "root", PASSWORD)
    page = harness.client.get("/admin")
    csrf = form_csrf(page.text)
    harness.client.post(f"/admin/submissions/{submission_id}/requeue", data={"csrf_token": csrf})
    status = harness.client.get(f"/api/submissions/{submission_id}").json()
    assert status["status"] == "queued"
    assert harness.work() is True
    assert harness.client.get(f"/api/submissions/{submission_id}").json()["status"] == "done"
    harness.client.post("/admin/challenges/toy/open", data={"is_open": "0", "csrf_token": csrf})
    closed = harness.client.post(
        "/api/uploads",
        json={"challenge": "toy", "size_bytes": 10},
        headers={"Authorization": f"Bearer {token}"},
    )
    assert closed.status_code == 400 and "closed" in closed.json()["error"]


def test_error_pages_are_html_and_api_errors_json(harness: Harness) -> None:
    page = harness.client.get("/challenges/nope")
    assert page.status_code == 404 and "text/html" in page.headers["content-type"]
    assert "no challenge named" in page.text
    api = harness.client.get("/api/challenges/nope")
    assert api.status_code == 404 and api.json() == {"error": "no challenge named 'nope'"}
