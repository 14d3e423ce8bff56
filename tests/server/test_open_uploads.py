"""Unfinished uploads can be listed and deleted (API, account page), so none blocks an account."""

from __future__ import annotations

from .conftest import (
    Harness,
    form_csrf,
    ground_truth_arrays,
    noisy_predictions,
    submission_zip,
    web_register,
)


def _open(harness: Harness, token: str, size: int = 1000, name: str = "preds.zip") -> str:
    response = harness.client.post(
        "/api/uploads",
        json={"challenge": "toy", "size_bytes": size, "filename": name},
        headers={"Authorization": f"Bearer {token}"},
    )
    assert response.status_code == 201, response.text
    return str(response.json()["id"])


def test_api_lists_and_deletes_the_callers_open_uploads(harness: Harness) -> None:
    token = harness.user_token("grace")
    headers = {"Authorization": f"Bearer {token}"}
    first = _open(harness, token, name="a.zip")
    second = _open(harness, token, name="b.zip")
    harness.client.put(
        f"/api/uploads/{first}", params={"offset": 0}, content=b"x" * 10, headers=headers
    )
    _open(harness, harness.user_token("mallory"), name="theirs.zip")

    listed = harness.client.get("/api/uploads", headers=headers)
    assert listed.status_code == 200
    body = listed.json()
    assert body["max_open_uploads"] == 3
    assert [(u["id"], u["filename"], u["received_bytes"]) for u in body["uploads"]] == [
        (first, "a.zip", 10),
        (second, "b.zip", 0),
    ]
    assert {"challenge", "size_bytes", "created_at", "expires_at", "complete"} <= set(
        body["uploads"][0]
    )

    assert harness.client.delete(f"/api/uploads/{first}", headers=headers).status_code == 204
    assert [
        u["id"] for u in harness.client.get("/api/uploads", headers=headers).json()["uploads"]
    ] == [second]
    assert harness.client.get("/api/uploads").status_code == 401


def test_a_full_account_is_told_how_to_free_it(harness: Harness) -> None:
    token = harness.user_token("grace")
    for _ in range(3):
        _open(harness, token)
    refused = harness.client.post(
        "/api/uploads",
        json={"challenge": "toy", "size_bytes": 10},
        headers={"Authorization": f"Bearer {token}"},
    )
    assert refused.status_code == 409
    assert "GET /api/uploads lists them" in refused.json()["error"]


def test_account_page_lists_open_uploads_with_delete_buttons(harness: Harness) -> None:
    client = harness.client
    assert web_register(client, "grace").status_code == 303
    page = client.get("/account")
    assert "Unfinished uploads" in page.text and "None." in page.text
    # An upload started from the browser and abandoned.
    csrf = form_csrf(page.text)
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    created = client.post(
        "/api/uploads",
        json={"challenge": "toy", "size_bytes": len(data), "filename": "abandoned.zip"},
        headers={"X-CSRF-Token": csrf},
    )
    assert created.status_code == 201
    upload_id = created.json()["id"]
    page = client.get("/account")
    assert "abandoned.zip" in page.text
    assert f'action="/account/uploads/{upload_id}/delete"' in page.text
    assert f"0 bytes of {len(data)} bytes" in page.text or "0 bytes of" in page.text

    deleted = client.post(
        f"/account/uploads/{upload_id}/delete", data={"csrf_token": csrf}, follow_redirects=False
    )
    assert deleted.status_code == 303
    assert "abandoned.zip" not in client.get("/account").text
    assert client.get("/api/uploads").json()["uploads"] == []


def test_submit_page_has_the_open_uploads_list_and_resume_script(harness: Harness) -> None:
    client = harness.client
    assert web_register(client, "grace").status_code == 303
    page = client.get("/submit")
    assert 'id="open-uploads-list"' in page.text
    assert 'max="10000000"' in page.text
    script = client.get("/static/upload.js").text
    assert 'api("GET", "/api/uploads")' in script
    assert "localStorage" in script
