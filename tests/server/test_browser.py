"""A real headless Chromium (Debian's, driven by Playwright): register, submit, see the result.

Never downloads a browser: uses /usr/bin/chromium and skips when it (or Playwright's
Python package) is absent. The final leaderboard screenshot is saved under
``$SEMANTIC3D_TEST_ARTIFACTS`` when set, else in the test's temporary folder.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from tests.browsers import chromium

from .conftest import ground_truth_arrays, noisy_predictions, submission_zip
from .processes import ServerProcess, environment, run_command

pytestmark = pytest.mark.slow


@pytest.fixture
def browser():
    with chromium(("--disable-gpu",)) as browser:
        yield browser


def test_register_submit_and_see_the_leaderboard(
    browser, tmp_path: Path, ground_truth_dir: Path
) -> None:
    data_dir = tmp_path / "data"
    added = run_command(
        [
            "admin",
            "add-challenge",
            "toy",
            "--ground-truth",
            str(ground_truth_dir),
            "--title",
            "Toy",
        ],
        environment(data_dir),
    )
    assert added.returncode == 0, added.stderr
    _show_confusion_matrices(data_dir, "toy")  # two scans would hide them by default
    preds = tmp_path / "my-predictions.zip"
    preds.write_bytes(submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)))
    server = ServerProcess(
        data_dir,
        tmp_path / "server.log",
        SEMANTIC3D_WORKER_POLL_S="0.2",
        SEMANTIC3D_SUBMISSION_COOLDOWN_H="0",
    )
    artifacts = Path(os.environ.get("SEMANTIC3D_TEST_ARTIFACTS", tmp_path))
    artifacts.mkdir(parents=True, exist_ok=True)
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    errors: list[str] = []
    page.on("console", lambda message: message.type == "error" and errors.append(message.text))
    try:
        page.goto(server.url + "/register")
        page.fill("input[name=username]", "grace")
        page.fill("input[name=password]", "a long password")
        page.fill("input[name=password_again]", "a long password")
        page.click("button[type=submit]")
        page.wait_for_url(re.compile(r".*/account$"))
        assert "Account grace" in page.content()

        page.goto(server.url + "/submit")
        page.select_option("select[name=challenge]", "toy")
        page.set_input_files("input[name=file]", str(preds))
        page.fill("input[name=name]", "Browser Forest")
        page.fill("textarea[name=description]", "Random forest on covariance features.")
        page.fill("input[name=code_url]", "https://example.org/forest")
        page.fill("input[name=runtime_s]", "5400")
        page.fill("input[name=hardware]", "8 CPU cores")
        page.click("#submit-button")
        page.wait_for_url(re.compile(r".*/submissions/\d+$"), timeout=60_000)
        page.wait_for_selector("#status.status-done", timeout=120_000)  # the page refreshes itself
        page.click("#publish")
        page.wait_for_selector("#unpublish")

        page.goto(server.url + "/challenges/toy")
        row = page.locator("#leaderboard tbody tr").first
        assert "Browser Forest" in row.inner_text()
        assert "90 min" in row.inner_text()
        page.screenshot(path=str(artifacts / "leaderboard.png"), full_page=True)
        page.click("text=Browser Forest")
        page.wait_for_selector("figure.heatmap svg")
        page.screenshot(path=str(artifacts / "method-page.png"), full_page=True)

        # A bad upload is explained on the page, every problem listed.
        page.goto(server.url + "/submit")
        bad = tmp_path / "bad.zip"
        bad.write_bytes(submission_zip({"scan_a": ground_truth_arrays()["scan_a"][:10] + 1}))
        page.set_input_files("input[name=file]", str(bad))
        page.fill("input[name=name]", "Broken")
        page.click("#submit-button")
        page.wait_for_selector("#upload-error p")
        assert "invalid submission" in page.inner_text("#upload-error")
        problems = page.locator("#upload-error #problems li").all_inner_texts()
        assert any("missing file 'scan_b.labels'" in p for p in problems)
        assert any("expected 3000 lines" in p for p in problems)
    finally:
        page.close()
        server.stop()
    assert (artifacts / "leaderboard.png").stat().st_size > 10_000
    assert not [e for e in errors if "Content Security Policy" in e], errors


def _show_confusion_matrices(data_dir: Path, challenge: str) -> None:
    from semantic3d.server.db import create_db_engine, create_session_factory
    from semantic3d.server.services.challenges import set_show_confusion
    from semantic3d.server.settings import Settings

    engine = create_db_engine(Settings(data_dir=data_dir))
    try:
        set_show_confusion(create_session_factory(engine), challenge, show=True)
    finally:
        engine.dispose()
