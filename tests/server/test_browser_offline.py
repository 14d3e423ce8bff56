"""Headless Chromium with every request off this server blocked: the API docs render, the
leaderboard sorts and filters by tag, and a reference row's method page renders (Debian's
/usr/bin/chromium through Playwright; skipped without it).

Screenshots go to ``$SEMANTIC3D_TEST_ARTIFACTS`` when set, else the test's temporary folder.
"""

from __future__ import annotations

import os
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from semantic3d.evaluation import MethodInfo
from tests.browsers import CHROMIUM

from .conftest import ground_truth_arrays, noisy_predictions, submission_zip
from .processes import ServerProcess, environment, run_command
from .test_browser import browser  # noqa: F401  (the fixture)

pytestmark = pytest.mark.slow


def _offline_page(browser, server_url: str, blocked: list[str]):  # noqa: F811
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    host = urlsplit(server_url).netloc

    def route(request_route) -> None:
        if urlsplit(request_route.request.url).netloc == host:
            request_route.continue_()
        else:
            blocked.append(request_route.request.url)
            request_route.abort()

    page.route("**/*", route)
    return page


def _seed(data_dir: Path, tmp_path: Path, ground_truth_dir: Path, server_url: str) -> None:
    from semantic3d.server.client import BenchmarkClient
    from semantic3d.server.db import create_db_engine, create_session_factory
    from semantic3d.server.services.accounts import create_token, create_user
    from semantic3d.server.settings import Settings

    engine = create_db_engine(Settings(data_dir=data_dir))
    factory = create_session_factory(engine)
    try:
        for index, (name, accuracy) in enumerate((("ada", 0.6), ("bob", 0.95), ("cyd", 0.8))):
            user = create_user(factory, name, "a long password")
            token = create_token(factory, user.id, "test")[1]
            path = tmp_path / f"{name}.zip"
            path.write_bytes(
                submission_zip(noisy_predictions(ground_truth_arrays(), accuracy, seed=index))
            )
            with BenchmarkClient(server_url, token) as client:
                queued = client.submit(
                    path,
                    challenge="toy",
                    method=MethodInfo(f"Method {name}", runtime_s=60.0 * (index + 1)),
                )
                assert client.wait(queued.id, poll_s=0.2, timeout_s=120).status == "done"
                client.publish(queued.id)
    finally:
        engine.dispose()


def test_docs_render_offline_and_the_leaderboard_sorts(
    browser,  # noqa: F811
    tmp_path: Path,
    ground_truth_dir: Path,
) -> None:
    data_dir = tmp_path / "data"
    added = run_command(
        ["admin", "add-challenge", "toy", "--ground-truth", str(ground_truth_dir)],
        environment(data_dir),
    )
    assert added.returncode == 0, added.stderr
    server = ServerProcess(
        data_dir,
        tmp_path / "server.log",
        SEMANTIC3D_WORKER_POLL_S="0.2",
        SEMANTIC3D_SUBMISSION_COOLDOWN_H="0",
        SEMANTIC3D_LEADERBOARD_CACHE_S="0",
    )
    artifacts = Path(os.environ.get("SEMANTIC3D_TEST_ARTIFACTS", tmp_path))
    artifacts.mkdir(parents=True, exist_ok=True)
    blocked: list[str] = []
    errors: list[str] = []
    page = _offline_page(browser, server.url, blocked)
    page.on("console", lambda message: message.type == "error" and errors.append(message.text))
    try:
        _seed(data_dir, tmp_path, ground_truth_dir, server.url)

        page.goto(server.url + "/api/docs")
        page.wait_for_selector(".opblock", timeout=30_000)
        operations = page.locator(".opblock-summary-path").all_inner_texts()
        assert any("/api/challenges/{name}/leaderboard" in text for text in operations)
        page.screenshot(path=str(artifacts / "api-docs.png"))

        page.goto(server.url + "/challenges/reduced-8")
        rows = page.locator("#leaderboard tbody tr")
        assert rows.count() == 8
        assert page.locator("tr[data-tag=paper-baseline]").count() == 3
        assert page.is_visible("#tag-filter")  # shown by the page's script
        page.uncheck("#tag-filter input[value=published]")
        assert page.locator("#leaderboard tbody tr:visible").count() == 3
        assert page.inner_text("#shown-count") == "3 rows"
        page.check("#tag-filter input[value=published]")
        assert page.locator("#leaderboard tbody tr:visible").count() == 8
        methods = page.locator("#leaderboard tbody tr td:nth-child(2) a.method")
        assert methods.all_inner_texts()[0] == "SCF-Net"
        page.click("#leaderboard thead th[data-column='9']")  # IoU of class 5, buildings
        assert methods.all_inner_texts()[:2] == ["RandLA-Net", "SCF-Net"]  # 95.7, 95.3
        page.click("#leaderboard thead th[data-column='0']")  # the board's own order again
        assert methods.all_inner_texts()[0] == "SCF-Net"
        page.screenshot(path=str(artifacts / "reference-board.png"), full_page=True)

        page.click("text=DeepNet")
        page.wait_for_selector("#method-card")
        assert page.inner_text("h1") == "DeepNet"
        assert "paper baseline" in page.inner_text("#tag")
        assert "nsavinov/semantic3dnet" in page.inner_text("#code")
        assert page.locator("#scores tbody td").count() == 2 + 8
        page.screenshot(path=str(artifacts / "reference-method-page.png"), full_page=True)

        page.goto(server.url + "/challenges/toy")
        methods = page.locator("#leaderboard tbody tr td:nth-child(2) a")
        assert methods.all_inner_texts() == ["Method bob", "Method cyd", "Method ada"]
        assert page.locator("#tag-filter").count() == 0  # one tag: nothing to filter
        page.click("#col-runtime")  # T (run time): highest first
        assert methods.all_inner_texts() == ["Method cyd", "Method bob", "Method ada"]
        page.click("#col-miou")  # mIoU: highest first
        assert methods.all_inner_texts() == ["Method bob", "Method cyd", "Method ada"]
        page.click("#col-miou")  # again: lowest first
        assert methods.all_inner_texts() == ["Method ada", "Method cyd", "Method bob"]
        assert page.get_attribute("#col-miou", "aria-sort") == "ascending"
        page.screenshot(path=str(artifacts / "sorted-board.png"), full_page=True)

        page.goto(server.url + "/login")
        page.fill("input[name=username]", "ada")
        page.fill("input[name=password]", "a long password")
        page.click("main button[type=submit]")
        page.goto(server.url + "/submit?challenge=toy")
        assert "--token s3d_" in page.inner_text("#cli-hint")
        assert "you can submit now" in page.inner_text("#cooldowns")
        page.screenshot(path=str(artifacts / "submit-page.png"), full_page=True)
    finally:
        page.close()
        server.stop()
    assert blocked == [], blocked  # nothing was asked of another host
    assert not [e for e in errors if "Content Security Policy" in e], errors
    assert CHROMIUM.exists()
