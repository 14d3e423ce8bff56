"""Leaderboard exports and sorting, the submit page's sizes and cooldown, offline API docs,
and the confusion-matrix policy."""

from __future__ import annotations

import csv
import io
import re
from html.parser import HTMLParser
from pathlib import Path

import pytest

from semantic3d.core.classes import CLASSES
from semantic3d.server.services.challenges import CONFUSION_MIN_SCANS, set_show_confusion
from semantic3d.server.services.leaderboard_export import CSV_COLUMNS, iou_column
from semantic3d.server.web import STATIC_DIR, format_bytes, format_duration

from .board_html import (
    FIRST_IOU,
    MEAN_IOU,
    METHOD,
    OVERALL_ACCURACY,
    RANK,
    RUNTIME,
    TAG,
    BoardTable,
)
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


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def _published(harness: Harness, token: str, accuracy: float, method: str, **card: object) -> int:
    data = submission_zip(
        noisy_predictions(ground_truth_arrays(), accuracy, seed=int(accuracy * 9))
    )
    submission_id = int(harness.submit(token, data, method, **card).json()["id"])
    assert harness.work()
    response = harness.client.post(
        f"/api/submissions/{submission_id}/publish",
        json={"published": True},
        headers=_bearer(token),
    )
    assert response.status_code == 200, response.text
    return submission_id


def _csv_rows(harness: Harness, name: str) -> list[dict[str, str]]:
    response = harness.client.get(f"/challenges/{name}/leaderboard.csv")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/csv")
    assert f'filename="{name}-leaderboard.csv"' in response.headers["content-disposition"]
    reader = csv.DictReader(io.StringIO(response.text))
    assert tuple(reader.fieldnames or ()) == CSV_COLUMNS
    return list(reader)


def test_csv_export_matches_the_json_board(harness: Harness) -> None:
    alice, bob = harness.user_token("alice"), harness.user_token("bob")
    _published(harness, alice, 0.6, "Forest", runtime_s=5400, hardware="8 cores")
    _published(harness, bob, 0.9, '=HYPERLINK("https://evil.example")', code_url="https://c.org")
    board = harness.client.get("/api/challenges/toy/leaderboard").json()["entries"]
    rows = _csv_rows(harness, "toy")
    assert [row["rank"] for row in rows] == ["1", "2"]
    assert {row["kind"] for row in rows} == {"participant"}
    for row, entry in zip(rows, board, strict=True):
        assert float(row["mean_iou"]) == entry["mean_iou"]  # full precision, not per cent
        assert float(row["overall_accuracy"]) == entry["overall_accuracy"]
        for cls in CLASSES:
            column = "iou_" + cls.name.replace("-", "_").replace(" ", "_")
            value = entry["iou"][str(cls.value)]
            assert (row[column] == "") if value is None else float(row[column]) == value
        assert int(row["submission_id"]) == entry["submission_id"]
        assert row["submitted_at"] == entry["submitted_at"]
    # A cell starting with a formula character cannot run in a spreadsheet.
    assert rows[0]["method"] == '\'=HYPERLINK("https://evil.example")'
    assert rows[1]["runtime_s"] == "5400.0" and rows[1]["hardware"] == "8 cores"


def test_csv_export_of_a_benchmark_board_lists_the_references_without_rank(
    harness: Harness,
) -> None:
    rows = _csv_rows(harness, "reduced-8")
    assert [row["method"] for row in rows][-3:] == ["TMLC-MSR", "DeepNet", "TML-PCR"]  # by mIoU
    assert rows[0]["method"] == "SCF-Net"
    assert all(row["kind"] == "reference" and row["rank"] == "" for row in rows)
    assert [row["position"] for row in rows] == [str(i) for i in range(1, len(rows) + 1)]
    deep_net = next(row for row in rows if row["method"] == "DeepNet")
    assert (deep_net["mean_iou"], deep_net["overall_accuracy"]) == ("0.437", "0.772")
    assert deep_net["runtime_s"] == "64800.0" and "1704.03847" in deep_net["paper_url"]
    assert deep_net["tag"] == "paper-baseline" and deep_net["source_year"] == "2017"
    assert deep_net["method_page"] == "/challenges/reduced-8/references/deepnet"
    assert "Hackel" in deep_net["source"] and "1704.03847" in deep_net["source_url"]
    randla = next(row for row in rows if row["method"] == "RandLA-Net")
    assert randla["tag"] == "published" and randla["runtime_s"] == ""  # not known: empty
    conv_point = next(r for r in _csv_rows(harness, "semantic-8") if r["method"] == "ConvPoint")
    assert conv_point["overall_accuracy"] == "" and conv_point["iou_cars"] == ""
    assert harness.client.get("/challenges/nope/leaderboard.csv").status_code == 404


def test_the_json_download_is_the_api_board(harness: Harness) -> None:
    for name in ("reduced-8", "toy"):
        download = harness.client.get(f"/challenges/{name}/leaderboard.json")
        assert download.status_code == 200
        assert download.headers["content-type"] == "application/json"
        assert f'filename="{name}-leaderboard.json"' in download.headers["content-disposition"]
        api = harness.client.get(f"/api/challenges/{name}/leaderboard")
        assert download.content == api.content
    assert harness.client.get("/challenges/nope/leaderboard.json").status_code == 404
    paths = harness.client.get("/api/openapi.json").json()["paths"]
    for path in (
        "/api/challenges/{name}/leaderboard",
        "/challenges/{name}/leaderboard.json",
        "/challenges/{name}/leaderboard.csv",
    ):
        assert "get" in paths[path], path


def test_csv_and_json_exports_match_the_page(harness: Harness) -> None:
    alice, bob = harness.user_token("alice"), harness.user_token("bob")
    _published(harness, alice, 0.6, "Forest", runtime_s=5400, hardware="8 cores")
    _published(harness, bob, 0.99, "Oracle", code_url="https://c.org")
    harness.state.leaderboards.invalidate()
    for name in ("toy", "reduced-8", "semantic-8"):
        page = BoardTable.parse(harness.client.get(f"/challenges/{name}").text).rows
        lines = _csv_rows(harness, name)
        board = harness.client.get(f"/api/challenges/{name}/leaderboard").json()
        api = sorted(board["entries"] + board["references"], key=lambda row: row["position"])
        assert len(page) == len(lines) == len(api) > 0
        for html, line, row in zip(page, lines, api, strict=True):
            assert html.method == line["method"] == row["method"]
            assert html.tag == line["tag"] == row["tag"]
            assert html.href == line["method_page"] == row["method_page"]
            rank = "" if row["rank"] is None else str(row["rank"])
            assert html.cells[RANK].value == line["rank"] == rank
            numbers = [
                (MEAN_IOU, "mean_iou", row["mean_iou"]),
                (OVERALL_ACCURACY, "overall_accuracy", row["overall_accuracy"]),
                (RUNTIME, "runtime_s", row["runtime_s"]),
            ] + [
                (FIRST_IOU + i, iou_column(cls.name), row["iou"][str(cls.value)])
                for i, cls in enumerate(CLASSES)
            ]
            for index, column, value in numbers:
                exported = float(line[column]) if line[column] else None
                assert html.number(index) == exported == value, (name, row["method"], column)
    toy = BoardTable.parse(harness.client.get("/challenges/toy").text).rows
    assert [row.method for row in toy] == ["Oracle", "Forest"]


def test_leaderboard_columns_are_sortable_by_a_local_script(harness: Harness) -> None:
    token = harness.user_token("alice")
    _published(harness, token, 0.8, "Forest", runtime_s=90)
    page = harness.client.get("/challenges/toy").text
    assert '<script src="/static/sort.js" defer></script>' in page
    assert 'class="board sortable"' in page
    table = BoardTable.parse(page)
    sortable = {
        int(str(h["data-column"])): h["data-sort"] for h in table.headings if h.get("data-sort")
    }
    assert sortable[RANK] == "position" and sortable[METHOD] == sortable[TAG] == "text"
    numeric = [MEAN_IOU, OVERALL_ACCURACY, *range(FIRST_IOU, RUNTIME + 1)]
    assert all(sortable[column] == "number" for column in numeric)
    # Grouped headings: "Overall" over mIoU and OA, "IoU per class" over the classes.
    groups = [h for h in table.headings if h.get("class") == "group"]
    assert [h["colspan"] for h in groups] == ["2", str(len(CLASSES))]
    (row,) = table.rows
    assert row.cells[RANK].value == "1" and (row.number(MEAN_IOU) or 0) > 0.5  # a fraction
    assert row.number(RUNTIME) == 90.0 and row.cells[RUNTIME].text == "90 s"
    assert row.tag == "verified" and row.href and row.href.startswith("/submissions/")
    for script in ("/static/sort.js", "/static/board.js"):
        response = harness.client.get(script)
        assert response.status_code == 200 and "javascript" in response.headers["content-type"]
        assert "http" not in response.text


def test_submit_page_shows_sizes_cooldown_and_a_complete_command(
    tmp_path: Path, ground_truth_dir: Path
) -> None:
    settings = make_settings(tmp_path / "data", submission_cooldown_h=72)
    harness_iter = build_harness(settings, ground_truth_dir)
    try:
        _check_submit_page(next(harness_iter))
    finally:
        harness_iter.close()


def _cooldown_text(page: str, name: str) -> str:
    match = re.search(rf'<li data-challenge="{name}">(.*?)</li>', page, re.S)
    assert match is not None, name
    return " ".join(re.sub(r"<[^>]+>", "", match.group(1)).split())


def _check_submit_page(harness: Harness) -> None:
    harness.user_token("alice")
    assert web_login(harness.client, "alice", PASSWORD).status_code == 303
    page = harness.client.get("/submit?challenge=toy").text
    assert "at most 8 GiB" in page
    hint = re.search(r'<pre id="cli-hint">(.*?)</pre>', page, re.S)
    assert hint is not None
    for option in ("--server http://testserver", "--challenge toy", "--token", "--method"):
        assert option in hint.group(1), option
    assert _cooldown_text(page, "toy") == "Toy challenge: you can submit now"
    assert _cooldown_text(page, "semantic-8").endswith("not open yet: ground truth not installed")
    assert "One submission per challenge every 3 d" in page

    api_token = harness.user_token("bob")
    harness.submit(api_token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.8)))
    harness.client.post("/logout", data={"csrf_token": form_csrf(page)})
    assert web_login(harness.client, "bob", PASSWORD).status_code == 303
    page = harness.client.get("/submit").text
    assert re.fullmatch(
        r"Toy challenge: next submission in (2 d 23 h|3 d) \(from .* UTC\)",
        _cooldown_text(page, "toy"),
    )
    assert "is being evaluated now" in page


def test_human_readable_sizes_and_waits() -> None:
    assert format_bytes(1_503_238_554) == "1.4 GiB"
    assert format_bytes(8 << 30) == "8 GiB"
    assert format_bytes(512 << 20) == "512 MiB"
    assert format_bytes(1536) == "1.5 KiB"
    assert format_bytes(0) == "0 bytes"
    assert format_duration(1) == "1 min"
    assert format_duration(72 * 3600) == "3 d"
    assert format_duration(90 * 60) == "1 h 30 min"
    assert format_duration(3601) == "1 h 1 min"  # rounded up: never says "now" too early


class _Links(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []
        self.inline_scripts = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = dict(attrs)
        for key in ("src", "href", "data-openapi-url"):
            if values.get(key):
                self.urls.append(str(values[key]))
        if tag == "script" and not values.get("src"):
            self.inline_scripts += 1


def test_api_docs_load_everything_from_this_server(harness: Harness) -> None:
    response = harness.client.get("/api/docs")
    assert response.status_code == 200
    links = _Links()
    links.feed(response.text)
    assert links.urls and all(url.startswith("/") for url in links.urls), links.urls
    assert "//" not in " ".join(links.urls)
    assert links.inline_scripts == 0
    policy = response.headers["content-security-policy"]
    assert "http" not in policy and "script-src 'self';" in policy
    for url in links.urls:
        if url.startswith("/static/"):
            asset = harness.client.get(url)
            assert asset.status_code == 200 and len(asset.content) > 0, url
    bundle = STATIC_DIR / "swagger-ui"
    assert (bundle / "LICENSE").read_text().startswith("\n") or "Apache" in (
        bundle / "LICENSE"
    ).read_text()
    assert "swagger-ui-dist" in (bundle / "SOURCE.txt").read_text()
    init = (bundle / "init.js").read_text()
    assert "validatorUrl: null" in init and "http" not in init
    assert harness.client.get("/api/openapi.json").json()["paths"]


def test_confusion_matrices_follow_the_challenge_policy(harness: Harness) -> None:
    token = harness.user_token("alice")
    submission_id = _published(harness, token, 0.9, "Forest")
    url = f"/api/submissions/{submission_id}"
    assert harness.client.get(url, headers=_bearer(token)).json()["scores"]["confusion"]

    # The toy has 2 scans: the rule (>= CONFUSION_MIN_SCANS scans) hides the matrix.
    assert CONFUSION_MIN_SCANS > 2
    set_show_confusion(harness.state.factory, "toy", show=None)
    harness.state.leaderboards.invalidate()
    for headers in (_bearer(token), {}):  # the owner too: the owner is who would read it
        scores = harness.client.get(url, headers=headers).json()["scores"]
        assert scores["confusion"] is None and scores["mean_iou"] > 0
    mine = harness.client.get("/api/submissions", headers=_bearer(token)).json()["submissions"]
    assert mine[0]["scores"]["confusion"] is None
    page = harness.client.get(f"/submissions/{submission_id}").text
    assert 'id="confusion-hidden"' in page and 'figure class="heatmap"' not in page
    board = harness.client.get("/challenges/toy").text
    assert "do not show confusion matrices" in board
    assert harness.client.get("/api/challenges/toy").json()["shows_confusion"] is False

    # Administrators see it, and can override the rule per challenge on /admin.
    admin_token = harness.user_token("root", admin=True)
    assert harness.client.get(url, headers=_bearer(admin_token)).json()["scores"]["confusion"]
    assert web_login(harness.client, "root", PASSWORD).status_code == 303
    csrf = form_csrf(harness.client.get("/admin").text)
    response = harness.client.post(
        "/admin/challenges/toy/confusion", data={"show": "show", "csrf_token": csrf}
    )
    assert response.status_code == 200
    assert harness.client.get(url, headers=_bearer(token)).json()["scores"]["confusion"]
    bad = harness.client.post(
        "/admin/challenges/toy/confusion", data={"show": "maybe", "csrf_token": csrf}
    )
    assert bad.status_code == 400


@pytest.mark.parametrize("name", ["semantic-8", "reduced-8"])
def test_benchmark_challenges_state_their_confusion_policy(harness: Harness, name: str) -> None:
    challenge = harness.client.get(f"/api/challenges/{name}").json()
    assert challenge["shows_confusion"] is (challenge["n_scans"] >= CONFUSION_MIN_SCANS)
    page = harness.client.get(f"/challenges/{name}").text
    expected = "show confusion matrices." if challenge["shows_confusion"] else "do not show"
    assert expected in page
