"""The API end to end in-process: upload, validate, queue, evaluate, publish, rank."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from semantic3d.evaluation import MethodInfo, evaluate_submission
from semantic3d.server.services.challenges import build_challenge, get_challenge

from .conftest import (
    Harness,
    ground_truth_arrays,
    noisy_predictions,
    submission_zip,
)


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def test_health_and_challenge_listing(harness: Harness) -> None:
    assert harness.client.get("/api/health").json()["status"] == "ok"
    challenges = harness.client.get("/api/challenges").json()["challenges"]
    # The benchmark's own challenges are listed from the start, before their ground truth.
    assert [c["name"] for c in challenges] == ["semantic-8", "reduced-8", "toy"]
    assert challenges[2]["n_scans"] == 2
    assert challenges[2]["n_points"] == 5000
    board = harness.client.get("/api/challenges/toy/leaderboard").json()
    assert board["entries"] == []
    assert harness.client.get("/api/challenges/nope/leaderboard").status_code == 404


def test_submission_is_scored_by_the_evaluation_function(harness: Harness, tmp_path: Path) -> None:
    token = harness.user_token("alice")
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.8))
    response = harness.submit(
        token, data, "PointNet-ish", runtime_s=3600, hardware="1 GPU", paper_url="https://x.org/p"
    )
    assert response.status_code == 201, response.text
    submission = response.json()
    assert submission["status"] == "queued"
    assert harness.work() is True
    assert harness.work() is False  # queue drained

    state = harness.client.get(f"/api/submissions/{submission['id']}", headers=_bearer(token))
    assert state.status_code == 200
    body = state.json()
    assert body["status"] == "done", body
    assert body["progress"]["done"] == body["progress"]["total"] > 0

    # The very function the CLI uses gives the very same numbers.
    path = tmp_path / "preds.zip"
    path.write_bytes(data)
    with harness.state.factory() as session:
        challenge = build_challenge(harness.settings, get_challenge(session, "toy"))
    method = MethodInfo(
        "PointNet-ish", runtime_s=3600, hardware="1 GPU", paper_url="https://x.org/p"
    )
    expected = evaluate_submission(path, challenge=challenge, method=method)
    assert body["scores"]["mean_iou"] == pytest.approx(expected.mean_iou, abs=0)
    assert body["scores"]["overall_accuracy"] == expected.overall_accuracy
    assert body["scores"]["confusion"] == expected.confusion.tolist()
    assert body["scores"]["n_points"] == expected.n_points


def test_results_are_private_until_published(harness: Harness) -> None:
    token = harness.user_token("alice")
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    submission_id = harness.submit(token, data).json()["id"]
    harness.work()

    anonymous = harness.client.get(f"/api/submissions/{submission_id}")
    assert anonymous.status_code == 404
    other = harness.user_token("bob")
    assert (
        harness.client.get(f"/api/submissions/{submission_id}", headers=_bearer(other)).status_code
        == 404
    )
    assert harness.client.get(f"/submissions/{submission_id}").status_code == 404
    assert harness.client.get("/api/challenges/toy/leaderboard").json()["entries"] == []

    # Someone else cannot publish it.
    steal = harness.client.post(
        f"/api/submissions/{submission_id}/publish",
        json={"published": True},
        headers=_bearer(other),
    )
    assert steal.status_code == 404
    published = harness.client.post(
        f"/api/submissions/{submission_id}/publish",
        json={"published": True},
        headers=_bearer(token),
    )
    assert published.status_code == 200 and published.json()["published"] is True
    entries = harness.client.get("/api/challenges/toy/leaderboard").json()["entries"]
    assert [e["submission_id"] for e in entries] == [submission_id]
    public = harness.client.get(f"/api/submissions/{submission_id}").json()
    assert public["scores"]["mean_iou"] == entries[0]["mean_iou"]
    assert "error" not in public and "filename" not in public  # owner-only fields

    harness.client.post(
        f"/api/submissions/{submission_id}/publish",
        json={"published": False},
        headers=_bearer(token),
    )
    assert harness.client.get("/api/challenges/toy/leaderboard").json()["entries"] == []


def test_leaderboard_ranks_by_mean_iou_server_side(harness: Harness) -> None:
    truth = ground_truth_arrays()
    ids = {}
    for user, accuracy in (("weak", 0.5), ("strong", 0.95), ("middle", 0.75)):
        token = harness.user_token(user)
        response = harness.submit(token, submission_zip(noisy_predictions(truth, accuracy)), user)
        ids[user] = response.json()["id"]
        harness.work()
        harness.client.post(
            f"/api/submissions/{ids[user]}/publish",
            json={"published": True},
            headers=_bearer(token),
        )
    entries = harness.client.get("/api/challenges/toy/leaderboard").json()["entries"]
    assert [e["method"] for e in entries] == ["strong", "middle", "weak"]
    assert [e["rank"] for e in entries] == [1, 2, 3]
    mious = [e["mean_iou"] for e in entries]
    assert mious == sorted(mious, reverse=True)
    assert set(entries[0]["iou"]) == {str(v) for v in range(1, 9)}
    page = harness.client.get("/challenges/toy").text
    assert page.index("strong") < page.index("middle") < page.index("weak")


def test_per_scan_scores_are_never_served(harness: Harness) -> None:
    token = harness.user_token("alice")
    submission_id = harness.submit(
        token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    ).json()["id"]
    harness.work()
    harness.client.post(
        f"/api/submissions/{submission_id}/publish",
        json={"published": True},
        headers=_bearer(token),
    )
    with harness.state.factory() as session:
        from semantic3d.server.models import Submission

        stored = json.loads(session.get(Submission, submission_id).result_json)
    assert len(stored["per_scan"]) == 2  # kept server-side...
    for url in (
        f"/api/submissions/{submission_id}",
        "/api/challenges/toy/leaderboard",
        f"/submissions/{submission_id}",
        "/api/submissions",
    ):
        text = harness.client.get(url, headers=_bearer(token)).text
        assert "per_scan" not in text and "scan_a" not in text, url  # ...never shown


def test_method_page_shows_the_confusion_heatmap(harness: Harness) -> None:
    token = harness.user_token("alice")
    submission_id = harness.submit(
        token,
        submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)),
        "<script>alert(1)</script>",
        code_url="https://example.org/code",
    ).json()["id"]
    harness.work()
    harness.client.post(
        f"/api/submissions/{submission_id}/publish",
        json={"published": True},
        headers=_bearer(token),
    )
    page = harness.client.get(f"/submissions/{submission_id}")
    assert page.status_code == 200
    assert "<svg" in page.text and "ground truth" in page.text
    assert page.text.count("<rect") >= 64
    assert "<script>alert(1)</script>" not in page.text  # escaped
    assert "&lt;script&gt;" in page.text
    board = harness.client.get("/challenges/toy").text
    assert "<script>alert(1)</script>" not in board and 'href="https://example.org/code"' in board


def test_upload_resumes_from_the_server_offset(harness: Harness) -> None:
    token = harness.user_token("alice")
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    headers = _bearer(token)
    created = harness.client.post(
        "/api/uploads", json={"challenge": "toy", "size_bytes": len(data)}, headers=headers
    ).json()
    upload_id = created["id"]
    half = len(data) // 2
    assert (
        harness.client.put(
            f"/api/uploads/{upload_id}", params={"offset": 0}, content=data[:half], headers=headers
        ).json()["received_bytes"]
        == half
    )
    # A chunk at the wrong offset is refused and told where to resume.
    wrong = harness.client.put(
        f"/api/uploads/{upload_id}", params={"offset": 0}, content=data[:10], headers=headers
    )
    assert wrong.status_code == 409 and wrong.json()["offset"] == half
    status = harness.client.get(f"/api/uploads/{upload_id}", headers=headers).json()
    assert status["received_bytes"] == half and status["complete"] is False
    done = harness.client.put(
        f"/api/uploads/{upload_id}", params={"offset": half}, content=data[half:], headers=headers
    )
    assert done.json()["complete"] is True
    response = harness.finalize(token, upload_id)
    assert response.status_code == 201, response.text
    with harness.state.factory() as session:
        from semantic3d.server.models import Submission

        stored = session.get(Submission, response.json()["id"])
        import hashlib

        assert stored.sha256 == hashlib.sha256(data).hexdigest()
        assert (harness.settings.submissions_dir / stored.stored_name).read_bytes() == data
        assert stored.stored_name != "preds.zip"


def test_create_with_sha256_resumes_the_same_upload(harness: Harness) -> None:
    import hashlib

    token = harness.user_token("alice")
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    body = {"challenge": "toy", "size_bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    first = harness.client.post("/api/uploads", json=body, headers=_bearer(token)).json()
    harness.client.put(
        f"/api/uploads/{first['id']}",
        params={"offset": 0},
        content=data[:100],
        headers=_bearer(token),
    )
    again = harness.client.post("/api/uploads", json=body, headers=_bearer(token)).json()
    assert again["id"] == first["id"] and again["received_bytes"] == 100


def test_corrupted_transfer_is_caught_by_sha256(harness: Harness) -> None:
    import hashlib

    token = harness.user_token("alice")
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    corrupted = bytearray(data)
    corrupted[100] ^= 0xFF
    upload_id = harness.upload(token, bytes(corrupted), sha256=hashlib.sha256(data).hexdigest())
    response = harness.finalize(token, upload_id)
    assert response.status_code == 400
    assert "corrupted in transit" in response.json()["error"]
    assert harness.stored_files() == []


def test_my_submissions_lists_status_and_errors(harness: Harness) -> None:
    token = harness.user_token("alice")
    submission_id = harness.submit(
        token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    ).json()["id"]
    mine = harness.client.get("/api/submissions", headers=_bearer(token)).json()["submissions"]
    assert [(s["id"], s["status"]) for s in mine] == [(submission_id, "queued")]
    # Break the stored file so that the evaluation fails: the owner sees why.
    with harness.state.factory() as session:
        from semantic3d.server.models import Submission

        stored = (
            harness.settings.submissions_dir / session.get(Submission, submission_id).stored_name
        )
    with zipfile.ZipFile(stored, "w") as archive:
        archive.writestr("scan_a.labels", "1\n")
    harness.work()
    mine = harness.client.get("/api/submissions", headers=_bearer(token)).json()["submissions"]
    assert mine[0]["status"] == "failed"
    assert "missing file 'scan_b.labels'" in mine[0]["error"]
    assert str(harness.settings.data_dir) not in mine[0]["error"]


def test_api_requires_a_valid_token(harness: Harness) -> None:
    body = {"challenge": "toy", "size_bytes": 10}
    assert harness.client.post("/api/uploads", json=body).status_code == 401
    bad = harness.client.post("/api/uploads", json=body, headers=_bearer("s3d_nope"))
    assert bad.status_code == 401 and "invalid" in bad.json()["error"]
    assert harness.client.get("/api/me", headers=_bearer("garbage")).status_code == 401
    token = harness.user_token("alice")
    assert harness.client.get("/api/me", headers=_bearer(token)).json()["username"] == "alice"


def test_finalize_rejects_bad_method_links(harness: Harness) -> None:
    token = harness.user_token("alice")
    upload_id = harness.upload(token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)))
    response = harness.finalize(token, upload_id, paper_url="javascript:alert(1)")
    assert response.status_code == 400
    assert "paper_url: expected an http(s) address" in response.json()["error"]


def test_numbers_survive_the_database_round_trip(harness: Harness) -> None:
    token = harness.user_token("alice")
    submission_id = harness.submit(
        token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.7))
    ).json()["id"]
    harness.work()
    body = harness.client.get(f"/api/submissions/{submission_id}", headers=_bearer(token)).json()
    confusion = np.array(body["scores"]["confusion"])
    assert confusion.shape == (8, 8)
    assert confusion.sum() == body["scores"]["n_points"]
    assert body["scores"]["overall_accuracy"] == pytest.approx(
        np.trace(confusion) / confusion.sum()
    )


def test_publishing_refreshes_cached_boards_at_once(tmp_path: Path, ground_truth_dir: Path) -> None:
    from .conftest import build_harness, make_settings

    harness_iter = build_harness(
        make_settings(tmp_path / "data", leaderboard_cache_s=3600), ground_truth_dir
    )
    harness = next(harness_iter)
    try:
        assert "No published results yet" in harness.client.get("/challenges/toy").text
        assert harness.client.get("/api/challenges/toy/leaderboard").json()["entries"] == []
        token = harness.user_token("alice")
        submission_id = harness.submit(
            token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)), "Cached"
        ).json()["id"]
        harness.work()
        harness.client.post(
            f"/api/submissions/{submission_id}/publish",
            json={"published": True},
            headers=_bearer(token),
        )
        assert "Cached" in harness.client.get("/challenges/toy").text
        entries = harness.client.get("/api/challenges/toy/leaderboard").json()["entries"]
        assert [e["method"] for e in entries] == ["Cached"]
    finally:
        harness_iter.close()


def test_an_upload_being_finalized_cannot_be_written_or_finalized_again(harness: Harness) -> None:
    from semantic3d.server.errors import ConflictError
    from semantic3d.server.services.upload_files import locked_part

    token = harness.user_token("alice")
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    upload_id = harness.client.post(
        "/api/uploads", json={"challenge": "toy", "size_bytes": len(data)}, headers=_bearer(token)
    ).json()["id"]
    harness.client.put(
        f"/api/uploads/{upload_id}",
        params={"offset": 0},
        content=data[:-10],
        headers=_bearer(token),
    )
    with locked_part(harness.settings, upload_id):  # as finalize holds it
        busy = harness.client.put(
            f"/api/uploads/{upload_id}",
            params={"offset": len(data) - 10},
            content=data[-10:],
            headers=_bearer(token),
        )
        assert busy.status_code == 409 and "another request" in busy.json()["error"]
        assert harness.finalize(token, upload_id).status_code == 409
        with pytest.raises(ConflictError), locked_part(harness.settings, upload_id):
            pass
    assert harness.client.put(
        f"/api/uploads/{upload_id}",
        params={"offset": len(data) - 10},
        content=data[-10:],
        headers=_bearer(token),
    ).json()["complete"]
    assert harness.finalize(token, upload_id).status_code == 201
