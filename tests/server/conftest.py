"""Fixtures for the server tests: a toy custom challenge, an app, accounts and uploads."""

from __future__ import annotations

import io
import json
import re
import warnings
import zipfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

pytest.importorskip("fastapi")


from semantic3d.io.labels import write_labels
from semantic3d.server.app import create_app
from semantic3d.server.services.accounts import create_token, create_user
from semantic3d.server.services.challenges import install_challenge
from semantic3d.server.settings import Settings
from semantic3d.server.web import ServerState
from semantic3d.server.worker import Worker

if TYPE_CHECKING:
    from fastapi.testclient import TestClient

PASSWORD = "correct horse battery"
SCAN_SIZES = {"scan_a": 3000, "scan_b": 2000}


def ground_truth_arrays(seed: int = 7) -> dict[str, np.ndarray]:
    """Deterministic ground truth (values 0..8) for the toy challenge's scans."""
    rng = np.random.default_rng(seed)
    return {name: rng.integers(0, 9, n).astype(np.uint8) for name, n in SCAN_SIZES.items()}


def noisy_predictions(truth: Mapping[str, np.ndarray], accuracy: float, seed: int = 1):
    """Predictions 1..8 that agree with ``truth`` on about ``accuracy`` of the points."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, y_true in truth.items():
        y_pred = np.where(y_true == 0, 1, y_true).astype(np.uint8)
        flip = rng.random(y_true.shape[0]) > accuracy
        y_pred[flip] = rng.integers(1, 9, int(flip.sum()))
        out[name] = y_pred
    return out


def labels_text(values: np.ndarray) -> bytes:
    """``.labels`` file content for ``values``."""
    return ("\n".join(str(int(v)) for v in values) + "\n").encode()


def zip_bytes(members: Mapping[str, bytes], *, compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    """A zip archive holding ``members`` (name -> content)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=compression) as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    return buffer.getvalue()


def submission_zip(predictions: Mapping[str, np.ndarray]) -> bytes:
    """A submission zip for the toy challenge."""
    return zip_bytes({f"{name}.labels": labels_text(v) for name, v in predictions.items()})


@pytest.fixture
def ground_truth_dir(tmp_path: Path) -> Path:
    """A folder of ground-truth ``.labels`` files (outside the server's data dir)."""
    folder = tmp_path / "hidden-gt"
    folder.mkdir()
    for name, values in ground_truth_arrays().items():
        write_labels(folder / f"{name}.labels", [values])
    return folder


def make_settings(data_dir: Path, **overrides: Any) -> Settings:
    """Test settings: no embedded worker, fixed secret, fast login throttling window."""
    values: dict[str, Any] = {
        "data_dir": data_dir,
        "embedded_worker": False,
        "secret_key": "test-secret-key-0123456789",
        "submission_cooldown_h": 0,
        "leaderboard_cache_s": 0,
    }
    values.update(overrides)
    return Settings(**values)


@dataclass
class Harness:
    """An app with the toy challenge installed, its state and a test client."""

    client: TestClient
    state: ServerState

    @property
    def settings(self) -> Settings:
        return self.state.settings

    def user_token(self, username: str, *, admin: bool = False) -> str:
        """Create an account and return an API token for it."""
        user = create_user(self.state.factory, username, PASSWORD, is_admin=admin)
        return create_token(self.state.factory, user.id, "test")[1]

    def upload(
        self, token: str, data: bytes, *, challenge: str = "toy", chunk: int = 1 << 20, **extra: Any
    ) -> str:
        """Upload ``data`` in chunks; returns the upload id."""
        headers = {"Authorization": f"Bearer {token}"}
        body = {"challenge": challenge, "size_bytes": len(data), "filename": "preds.zip"} | extra
        response = self.client.post("/api/uploads", json=body, headers=headers)
        assert response.status_code == 201, response.text
        upload_id = response.json()["id"]
        offset = response.json()["received_bytes"]
        while offset < len(data):
            piece = data[offset : offset + chunk]
            response = self.client.put(
                f"/api/uploads/{upload_id}",
                params={"offset": offset},
                content=piece,
                headers=headers,
            )
            assert response.status_code == 200, response.text
            offset = response.json()["received_bytes"]
        return str(upload_id)

    def finalize(self, token: str, upload_id: str, method: str = "my method", **card: Any):
        """POST finalize; returns the response."""
        return self.client.post(
            f"/api/uploads/{upload_id}/finalize",
            json={"method": {"name": method} | card},
            headers={"Authorization": f"Bearer {token}"},
        )

    def submit(self, token: str, data: bytes, method: str = "my method", **card: Any):
        """Upload and finalize ``data``; returns the finalize response."""
        return self.finalize(token, self.upload(token, data), method, **card)

    def work(self) -> bool:
        """Let one worker evaluate one queued job."""
        return Worker(self.settings, self.state.factory, cache=self.state.challenges).run_once()

    def stored_files(self) -> list[Path]:
        """Every file under the uploads and submissions folders."""
        found = []
        for folder in (self.settings.uploads_dir, self.settings.submissions_dir):
            found.extend(p for p in folder.rglob("*") if p.is_file())
        return found


def build_harness(settings: Settings, ground_truth_dir: Path) -> Iterator[Harness]:
    """Create the app, install the toy challenge, and yield a harness with a test client."""
    with warnings.catch_warnings():
        # Starlette announces a future switch of its test client to httpx2; not ours to act on.
        warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
        from fastapi.testclient import TestClient

    app = create_app(settings)
    state: ServerState = app.state.server
    # Two scans would hide confusion matrices by default; the toy shows them to test them.
    install_challenge(
        state.factory,
        settings,
        "toy",
        ground_truth_dir,
        title="Toy challenge",
        show_confusion=True,
    )
    with TestClient(app) as client:
        yield Harness(client=client, state=state)


@pytest.fixture
def harness(tmp_path: Path, ground_truth_dir: Path) -> Iterator[Harness]:
    """A fresh server (SQLite) with the toy challenge and no cooldown."""
    yield from build_harness(make_settings(tmp_path / "data"), ground_truth_dir)


def form_csrf(html: str) -> str:
    """The CSRF token of the first form on a page."""
    match = re.search(r'name="csrf_token" value="([^"]+)"', html)
    assert match, "no CSRF token on the page"
    return match.group(1)


def web_register(client: TestClient, username: str, password: str = PASSWORD) -> Any:
    """Register through the web form (the client keeps the session cookie)."""
    page = client.get("/register")
    return client.post(
        "/register",
        data={
            "username": username,
            "password": password,
            "password_again": password,
            "csrf_token": form_csrf(page.text),
        },
        follow_redirects=False,
    )


def web_login(client: TestClient, username: str, password: str) -> Any:
    """Log in through the web form."""
    page = client.get("/login")
    return client.post(
        "/login",
        data={"username": username, "password": password, "csrf_token": form_csrf(page.text)},
        follow_redirects=False,
    )


def check_score_migration(engine: Any) -> None:
    """Migration 0004 on ``engine``'s empty database: 0003 -> head drops the ``n_points``
    copy and keeps the scores; head -> 0003 restores it from ``result_json``."""
    from alembic import command
    from alembic.config import Config
    from sqlalchemy import inspect, text

    from semantic3d.server.db import MIGRATIONS_DIR, run_migrations

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))

    def migrate(step: Any, revision: str) -> None:
        with engine.begin() as connection:
            config.attributes["connection"] = connection
            step(config, revision)

    migrate(command.upgrade, "0003")
    with engine.begin() as connection:
        connection.execute(
            text(
                "INSERT INTO users (username, password_hash, is_admin, created_at, quota_epoch, "
                "session_epoch) VALUES ('old', 'x', :no, :at, 0, 0)"
            ),
            {"no": False, "at": datetime(2026, 1, 1)},
        )
        connection.execute(
            text(
                "INSERT INTO submissions (user_id, challenge_id, created_at, in_flight, "
                "method_name, description, paper_url, code_url, filename, stored_name, "
                "size_bytes, sha256, published, mean_iou, overall_accuracy, iou_json, "
                "n_points, result_json) SELECT u.id, c.id, :at, :no, 'm', '', '', '', "
                "'p.zip', 's.zip', 1, 'x', :yes, 0.5, 0.75, '[0.5]', 1234, :result "
                "FROM users u, challenges c WHERE u.username = 'old' AND c.name = 'reduced-8'"
            ),
            {
                "at": datetime(2026, 1, 2),
                "no": False,
                "yes": True,
                "result": json.dumps({"n_points": 1234}),
            },
        )
    run_migrations(engine)
    columns = {column["name"] for column in inspect(engine).get_columns("submissions")}
    assert "n_points" not in columns and {"mean_iou", "iou_json", "result_json"} <= columns
    with engine.connect() as connection:
        row = connection.execute(
            text("SELECT mean_iou, overall_accuracy, iou_json, result_json FROM submissions")
        ).one()
    assert tuple(row) == (0.5, 0.75, "[0.5]", json.dumps({"n_points": 1234}))
    migrate(command.downgrade, "0003")
    with engine.connect() as connection:
        assert connection.execute(text("SELECT n_points FROM submissions")).scalar() == 1234
    run_migrations(engine)
