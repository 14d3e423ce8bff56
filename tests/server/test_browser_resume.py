"""Headless Chromium: an interrupted browser upload resumes; an abandoned one can be deleted.

Uses Debian's /usr/bin/chromium through Playwright (never a downloaded browser) and skips
without them, like ``test_browser.py``.
"""

from __future__ import annotations

import io
import re
import zipfile
from pathlib import Path

import pytest

from .conftest import ground_truth_arrays, labels_text, noisy_predictions
from .processes import ServerProcess, environment, run_command
from .test_browser import browser  # noqa: F401  (the fixture)

pytestmark = pytest.mark.slow

CHUNK = 16 << 20  # upload.js's chunk size
CHUNK_URL = re.compile(r".*/api/uploads/[0-9a-f]{32}\?offset=.*")


def two_chunk_submission(path: Path) -> Path:
    """A valid toy submission over 16 MiB: the labels plus ignored ``__MACOSX`` padding."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, values in noisy_predictions(ground_truth_arrays(), 0.9).items():
            archive.writestr(f"{name}.labels", labels_text(values), zipfile.ZIP_DEFLATED)
        archive.writestr("__MACOSX/padding", b"\0" * (CHUNK + (1 << 20)), zipfile.ZIP_STORED)
    path.write_bytes(buffer.getvalue())
    return path


def test_an_interrupted_upload_resumes_and_an_abandoned_one_is_deleted(
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
    preds = two_chunk_submission(tmp_path / "preds.zip")
    server = ServerProcess(
        data_dir,
        tmp_path / "server.log",
        SEMANTIC3D_WORKER_POLL_S="0.2",
        SEMANTIC3D_SUBMISSION_COOLDOWN_H="0",
    )
    page = browser.new_page()
    requests: list[tuple[str, str]] = []
    page.on("request", lambda r: "/api/uploads" in r.url and requests.append((r.method, r.url)))
    interrupted: list[str] = []

    def cut_second_chunk(route) -> None:
        if "offset=0" not in route.request.url and not interrupted:
            interrupted.append(route.request.url)
            route.abort()
        else:
            route.continue_()

    def fill_form() -> None:
        page.select_option("select[name=challenge]", "toy")
        page.set_input_files("input[name=file]", str(preds))
        page.fill("input[name=name]", "Resumed")

    def upload_until_cut() -> None:
        """Start an upload, cut it after its first chunk and leave the page."""
        interrupted.clear()
        page.route(CHUNK_URL, cut_second_chunk)
        page.goto(server.url + "/submit")
        fill_form()
        page.click("#submit-button")
        for _ in range(600):
            if interrupted:
                break
            page.wait_for_timeout(100)
        assert interrupted, "the second chunk was never sent"
        page.unroute(CHUNK_URL)
        page.goto(server.url + "/submit")

    try:
        page.goto(server.url + "/register")
        page.fill("input[name=username]", "grace")
        page.fill("input[name=password]", "a long password")
        page.fill("input[name=password_again]", "a long password")
        page.click("button[type=submit]")
        page.wait_for_url(re.compile(r".*/account$"))

        upload_until_cut()
        # The user comes back later: the page lists the unfinished upload ...
        page.wait_for_selector("#open-uploads-list li")
        assert "preds.zip (toy): 16.0 MiB of" in page.inner_text("#open-uploads-list")
        # ... and choosing the same file again continues where it stopped.
        requests.clear()
        fill_form()
        page.click("#submit-button")
        page.wait_for_url(re.compile(r".*/submissions/\d+$"), timeout=60_000)
        assert ("POST", server.url + "/api/uploads") not in requests
        puts = [url for method, url in requests if method == "PUT"]
        assert puts and all(url.endswith(f"offset={CHUNK}") for url in puts), puts

        # An upload abandoned halfway is deleted from the list.
        upload_until_cut()
        page.wait_for_selector("#open-uploads-list li button.delete-upload")
        page.click("#open-uploads-list li button.delete-upload")
        page.wait_for_selector("#open-uploads", state="hidden")
        assert page.evaluate("fetch('/api/uploads').then(r => r.json())")["uploads"] == []
    finally:
        page.close()
        server.stop()
