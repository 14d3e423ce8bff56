"""Real processes on 127.0.0.1: serve + the submit CLI, restarts, a worker killed mid-job."""

from __future__ import annotations

import hashlib
import json
import signal
import sqlite3
import time
import zipfile
from contextlib import closing
from pathlib import Path

import httpx
import numpy as np
import pytest

from semantic3d.evaluation import MethodInfo, evaluate_submission
from semantic3d.io.labels import format_labels_bytes, write_labels
from semantic3d.server.client import BenchmarkClient
from semantic3d.server.db import create_db_engine, create_session_factory
from semantic3d.server.services.challenges import build_challenge, get_challenge
from semantic3d.server.settings import Settings

from .conftest import PASSWORD, form_csrf, ground_truth_arrays, noisy_predictions, submission_zip
from .processes import ServerProcess, WorkerProcess, environment, run_command

pytestmark = pytest.mark.slow


def setup_server(data_dir: Path, ground_truth: Path, *, challenge: str = "toy") -> str:
    """Install the challenge and an account through the admin commands; returns a token."""
    env = environment(data_dir)
    added = run_command(
        ["admin", "add-challenge", challenge, "--ground-truth", str(ground_truth)], env
    )
    assert added.returncode == 0, added.stderr
    user = run_command(["admin", "create-user", "alice"], env, input=f"{PASSWORD}\n{PASSWORD}\n")
    assert user.returncode == 0, user.stderr
    token = run_command(["admin", "create-token", "alice"], env)
    assert token.returncode == 0, token.stderr
    return token.stdout.strip()


def wait_for(predicate, timeout_s: float = 120.0, interval_s: float = 0.05):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval_s)
    raise AssertionError(f"condition not met within {timeout_s} s")


def test_serve_and_submit_end_to_end(tmp_path: Path, ground_truth_dir: Path) -> None:
    data_dir = tmp_path / "data"
    token = setup_server(data_dir, ground_truth_dir)
    preds = tmp_path / "preds.zip"
    preds.write_bytes(submission_zip(noisy_predictions(ground_truth_arrays(), 0.85)))
    server = ServerProcess(data_dir, tmp_path / "server.log")  # SQLite: embedded worker
    try:
        result = run_command(
            [
                "submit",
                str(preds),
                "--server",
                server.url,
                "--challenge",
                "toy",
                "--method",
                "CLI method",
                "--runtime-s",
                "42",
                "--hardware",
                "laptop",
                "--publish",
                "--chunk-mib",
                "1",
            ],
            environment(data_dir, SEMANTIC3D_TOKEN=token),
        )
        assert result.returncode == 0, result.stdout + result.stderr
        assert "mIoU" in result.stdout and "published" in result.stdout
        board = httpx.get(f"{server.url}/api/challenges/toy/leaderboard").json()
        assert [e["method"] for e in board["entries"]] == ["CLI method"]
        assert board["entries"][0]["runtime_s"] == 42
        bad = run_command(
            ["submit", str(preds), "--server", server.url, "--challenge", "toy", "--method", "x"],
            environment(data_dir, SEMANTIC3D_TOKEN="s3d_wrong"),
        )
        assert bad.returncode == 2 and "401" in bad.stderr
    finally:
        server.stop()


def test_a_restart_loses_nothing(tmp_path: Path, ground_truth_dir: Path) -> None:
    data_dir = tmp_path / "data"
    token = setup_server(data_dir, ground_truth_dir)
    log = tmp_path / "server.log"
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    preds = tmp_path / "preds.zip"
    preds.write_bytes(data)

    server = ServerProcess(data_dir, log, "--no-worker")
    web = httpx.Client(base_url=server.url)
    page = web.get("/login")
    web.post(
        "/login",
        data={"username": "alice", "password": PASSWORD, "csrf_token": form_csrf(page.text)},
    )
    assert web.get("/account").status_code == 200
    # Half an upload, then the server dies.
    with BenchmarkClient(server.url, token) as client:
        created = client.open_upload(
            challenge="toy",
            size_bytes=len(data),
            filename="preds.zip",
            sha256=hashlib.sha256(data).hexdigest(),
        )
        client._http.put(f"/api/uploads/{created.id}", params={"offset": 0}, content=data[:1000])
    server.kill()

    server = ServerProcess(data_dir, log, "--no-worker")
    web.base_url = httpx.URL(server.url)
    with BenchmarkClient(server.url, token) as client:
        seen: list[int] = []
        upload_id = client.upload(preds, challenge="toy", progress=lambda d, t: seen.append(d))
        assert upload_id == created.id and seen[0] == 1000  # resumed, not restarted
        submission = client.finalize(upload_id, method=MethodInfo("survivor"))
    server.kill()  # dies with the job queued

    server = ServerProcess(data_dir, log)  # embedded worker picks the job up
    web.base_url = httpx.URL(server.url)
    with BenchmarkClient(server.url, token) as client:
        final = client.wait(submission.id, poll_s=0.2, timeout_s=120)
        assert final.status == "done"
        client.publish(submission.id)
        board = client.leaderboard("toy")
    server.stop()

    server = ServerProcess(data_dir, log, "--no-worker")
    web.base_url = httpx.URL(server.url)
    try:
        with BenchmarkClient(server.url, token) as client:
            assert client.leaderboard("toy") == board
            assert client.me().username == "alice"
        assert "Account alice" in web.get("/account").text  # the session cookie still works
    finally:
        server.stop()
        web.close()


def _slow_challenge(tmp_path: Path, n: int = 5_000_000) -> tuple[Path, Path]:
    """Ground truth with 2 x n points and a bzip2 submission (slow to inflate: seconds)."""
    rng = np.random.default_rng(3)
    folder = tmp_path / "big-gt"
    folder.mkdir()
    preds = tmp_path / "big.zip"
    with zipfile.ZipFile(preds, "w", zipfile.ZIP_BZIP2) as archive:
        for name in ("north", "south"):
            truth = rng.integers(0, 9, n).astype(np.uint8)
            write_labels(folder / f"{name}.labels", [truth])
            pred = np.where(rng.random(n) < 0.7, np.maximum(truth, 1), rng.integers(1, 9, n))
            archive.writestr(f"{name}.labels", bytes(format_labels_bytes(pred.astype(np.uint8))))
    return folder, preds


def _job_row(data_dir: Path, submission_id: int) -> dict:
    with closing(sqlite3.connect(data_dir / "semantic3d.sqlite3")) as db:
        db.row_factory = sqlite3.Row
        row = db.execute("SELECT * FROM jobs WHERE submission_id = ?", (submission_id,)).fetchone()
        return dict(row)


def _stop_mid_evaluation(worker: WorkerProcess, data_dir: Path, submission_id: int) -> dict:
    """Freeze ``worker`` (SIGSTOP) once it has reported progress on the job, not finished it.

    The worker is let run in short slices, so the moment is caught whatever the machine's
    speed; returns the job's row at that moment.
    """
    wait_for(lambda: _job_row(data_dir, submission_id)["status"] != "queued", interval_s=0.01)
    worker.process.send_signal(signal.SIGSTOP)
    for _ in range(2000):
        row = _job_row(data_dir, submission_id)
        assert row["status"] == "running", f"the job finished before it could be interrupted: {row}"
        if row["progress_done"] > 0:
            return row
        worker.process.send_signal(signal.SIGCONT)
        time.sleep(0.05)
        worker.process.send_signal(signal.SIGSTOP)
        time.sleep(0.05)  # let a heartbeat that was under way land
    raise AssertionError("the worker never reported progress")


def test_a_worker_killed_mid_job_is_replaced_with_the_identical_result(tmp_path: Path) -> None:
    ground_truth, preds = _slow_challenge(tmp_path)
    data_dir = tmp_path / "data"
    token = setup_server(data_dir, ground_truth, challenge="big")
    lease = {"SEMANTIC3D_JOB_LEASE_S": "0.9", "SEMANTIC3D_WORKER_POLL_S": "0.2"}
    server = ServerProcess(data_dir, tmp_path / "server.log", "--no-worker")
    try:
        with BenchmarkClient(server.url, token) as client:
            submission = client.submit(preds, challenge="big", method=MethodInfo("crash test"))
        submission_id = submission.id
        victim = WorkerProcess(data_dir, tmp_path / "worker-1.log", **lease)
        job = _stop_mid_evaluation(victim, data_dir, submission_id)
        victim.kill()  # SIGKILL mid-evaluation
        assert job["attempts"] == 1 and job["status"] == "running"
        assert 0 < job["progress_done"] < job["progress_total"]
        assert _job_row(data_dir, submission_id)["status"] == "running"  # until the lease ends

        rescuer = WorkerProcess(data_dir, tmp_path / "worker-2.log", **lease)
        try:
            done = wait_for(
                lambda: (
                    (row := _job_row(data_dir, submission_id))["status"] in ("done", "failed")
                    and row
                ),
                timeout_s=180,
            )
        finally:
            assert rescuer.stop() == 0  # SIGTERM: a clean exit
        assert done["status"] == "done", done
        assert done["attempts"] == 2 and done["leased_by"] != job["leased_by"]
    finally:
        server.stop()

    settings = Settings(data_dir=data_dir)
    factory = create_session_factory(create_db_engine(settings))
    with factory() as session:
        challenge = build_challenge(settings, get_challenge(session, "big"))
    with closing(sqlite3.connect(data_dir / "semantic3d.sqlite3")) as db:
        stored = db.execute(
            "SELECT result_json FROM submissions WHERE id = ?", (submission_id,)
        ).fetchone()[0]
    expected = evaluate_submission(preds, challenge=challenge, method=MethodInfo("crash test"))
    assert json.loads(stored) == json.loads(json.dumps(expected.to_dict()))
