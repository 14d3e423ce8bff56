"""The benchmark's own challenges on a fresh server, and the reference rows of their boards:
the paper's tables and later published records, tagged, sourced, sorted in unranked."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from pathlib import Path

import pytest
from sqlalchemy import select, text

from semantic3d.core.classes import CLASSES
from semantic3d.core.errors import DataFormatError
from semantic3d.evaluation import load_challenge
from semantic3d.server.db import create_db_engine, create_session_factory, run_migrations
from semantic3d.server.errors import InvalidInputError
from semantic3d.server.models import ChallengeRecord
from semantic3d.server.references import read_reference_results, reference_results
from semantic3d.server.services import challenges as challenges_module
from semantic3d.server.services.challenges import (
    NOT_INSTALLED,
    get_challenge,
    install_challenge,
    set_challenge_open,
)
from semantic3d.server.services.leaderboard import LeaderboardEntry, merged_rows

from .board_html import BoardTable
from .conftest import (
    PASSWORD,
    Harness,
    form_csrf,
    ground_truth_arrays,
    make_settings,
    noisy_predictions,
    submission_zip,
    web_login,
)

# The paper's rows, by challenge, in the order of its tables.
PAPER_ROWS = {
    "semantic-8": ["HarrisNet", "DeepSegNet", "TMLC-MS", "TML-PC"],
    "reduced-8": ["TMLC-MSR", "DeepNet", "TML-PCR"],
}
# Every reference row of each board, in the board's order (by mean IoU).
BOARD_ORDER = {
    "semantic-8": ["ConvPoint", "HarrisNet", "DeepSegNet", "TMLC-MS", "TML-PC"],
    "reduced-8": [
        "SCF-Net", "RandLA-Net", "RGNet", "KPConv", "SPG", "TMLC-MSR", "DeepNet", "TML-PCR",
    ],
}  # fmt: skip
PAPER_BASELINES = {"TMLC-MS", "TML-PC", "TMLC-MSR", "DeepNet", "TML-PCR"}


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def test_a_fresh_server_lists_both_benchmark_challenges_without_ground_truth(
    harness: Harness,
) -> None:
    listed = {c["name"]: c for c in harness.client.get("/api/challenges").json()["challenges"]}
    for name, n_scans in (("semantic-8", 15), ("reduced-8", 4)):
        challenge = listed[name]
        assert challenge["kind"] == name and challenge["n_scans"] == n_scans
        assert challenge["ground_truth_installed"] is False
        assert challenge["accepts_submissions"] is False
        assert challenge["status"] == NOT_INSTALLED
        assert challenge["n_points"] == sum(
            scan.n_points or 0 for scan in load_challenge(name, ground_truth_root=None).scans
        )
    assert listed["toy"]["status"] == "open" and listed["toy"]["accepts_submissions"]

    index = harness.client.get("/").text
    assert index.count(NOT_INSTALLED) == 2
    assert 'href="/submit?challenge=semantic-8"' not in index
    assert 'href="/submit?challenge=toy"' in index


def test_the_boards_show_the_references_tagged_sourced_and_unranked(harness: Harness) -> None:
    for name, methods in BOARD_ORDER.items():
        board = harness.client.get(f"/api/challenges/{name}/leaderboard").json()
        assert board["entries"] == []
        references = sorted(board["references"], key=lambda row: row["position"])
        assert [row["method"] for row in references] == methods
        assert [row["position"] for row in references] == list(range(1, len(methods) + 1))
        assert all(row["reference"] and row["rank"] is None for row in references)
        for row in references:
            expected = "paper-baseline" if row["method"] in PAPER_BASELINES else "published"
            assert row["tag"] == expected, row["method"]
            assert row["source"]["url"].startswith("https://") and row["source"]["year"] >= 2017
            assert row["method_page"] == f"/challenges/{name}/references/" + (row["method"].lower())
        assert "1704.03847" in board["reference_source"]["url"]
        assert "Hackel" in board["reference_source"]["citation"]
    rows = {
        row["method"]: row
        for row in harness.client.get("/api/challenges/reduced-8/leaderboard").json()["references"]
    }
    deep_net = rows["DeepNet"]
    assert (deep_net["mean_iou"], deep_net["overall_accuracy"]) == (0.437, 0.772)
    assert deep_net["runtime_s"] == 64_800
    assert deep_net["code_url"] == "https://github.com/nsavinov/semantic3dnet"
    scf = rows["SCF-Net"]
    assert (scf["mean_iou"], scf["overall_accuracy"], scf["runtime_s"]) == (0.776, 0.947, 563.6)
    assert scf["source"]["year"] == 2021 and scf["table"] == "Table 2"
    assert rows["RandLA-Net"]["iou"]["1"] == 0.956 and rows["RandLA-Net"]["runtime_s"] is None
    semantic = harness.client.get("/api/challenges/semantic-8/leaderboard").json()
    conv_point = next(row for row in semantic["references"] if row["method"] == "ConvPoint")
    assert conv_point["mean_iou"] == 0.765 and conv_point["overall_accuracy"] is None
    assert set(conv_point["iou"].values()) == {None}  # not sourced: left empty

    page = harness.client.get("/challenges/reduced-8").text
    assert page.count('data-tag="paper-baseline"') == 3
    assert page.count('data-tag="published"') == 5
    assert 'id="tag-filter"' in page and 'src="/static/board.js"' in page
    assert 'id="not-installed"' in page and NOT_INSTALLED in page
    assert "ground-truth" not in page  # no data paths or admin commands on public pages
    assert "Submit to this challenge" not in page
    assert "43.7" in page and "77.2" in page and ">18 h<" in page
    assert 'title="64,800 s"' in page
    for source in ("arxiv.org/abs/1704.03847", "arxiv.org/abs/1911.11236", "CVPR2021"):
        assert source in page

    # A custom challenge has no reference rows and no filter.
    toy = harness.client.get("/api/challenges/toy/leaderboard").json()
    assert toy["references"] == [] and toy["reference_source"] is None
    toy_page = harness.client.get("/challenges/toy").text
    assert 'data-tag="published"' not in toy_page and 'id="tag-filter"' not in toy_page


def test_a_reference_rows_method_page(harness: Harness) -> None:
    page = harness.client.get("/challenges/reduced-8/references/deepnet")
    assert page.status_code == 200
    html = page.text
    assert "<h1>DeepNet</h1>" in html and 'id="tag"' in html and "paper baseline" in html
    assert "Table 2 of Hackel" in html and "https://arxiv.org/abs/1704.03847" in html
    assert "https://github.com/nsavinov/semantic3dnet" in html
    assert "Titan X" in html and "18 h (64,800 s)" in html
    table = BoardTable()
    table.feed(html.replace('id="scores"', 'id="leaderboard"').replace("<thead>", "<thead>"))
    assert [cell.value for cell in table.rows[0].cells[:2]] == ["0.437", "0.772"]
    assert "No confusion matrix: the source publishes none" in html
    assert "deviation from the semantic3D.net paper" in html  # reduced-8 hides matrices

    tml = harness.client.get("/challenges/reduced-8/references/tml-pcr").text
    assert '<sup class="mark">*</sup>' in tml and "not present in the image data" in tml
    spg = harness.client.get("/challenges/reduced-8/references/spg").text
    assert "0.832" in spg and "SCF-Net" in spg  # where the values come from
    # A value not read from its source says so; what the paper does not describe is not
    # put in its mouth.
    conv_point = harness.client.get("/challenges/semantic-8/references/convpoint").text
    assert "the mIoU was not re-read from the paper" in conv_point
    tml_pc = harness.client.get("/challenges/semantic-8/references/tml-pc").text
    assert "back to the points the paper does not say" in tml_pc
    assert (
        'id="paper">none published'
        in harness.client.get("/challenges/semantic-8/references/harrisnet").text
    )
    for missing in (
        "/challenges/reduced-8/references/harrisnet",  # a semantic-8 row
        "/challenges/reduced-8/references/nope",
        "/challenges/toy/references/deepnet",
        "/challenges/nope/references/deepnet",
    ):
        assert harness.client.get(missing).status_code == 404, missing


def test_no_upload_or_opening_before_the_ground_truth_is_installed(harness: Harness) -> None:
    token = harness.user_token("alice")
    response = harness.client.post(
        "/api/uploads",
        json={"challenge": "semantic-8", "size_bytes": 100, "filename": "p.zip"},
        headers=_bearer(token),
    )
    assert response.status_code == 400
    assert NOT_INSTALLED in response.json()["error"]
    with pytest.raises(InvalidInputError, match="ground truth not installed"):
        set_challenge_open(harness.state.factory, "semantic-8", is_open=True)
    with harness.state.factory() as session:
        assert get_challenge(session, "semantic-8").is_open is False

    harness.user_token("root", admin=True)
    assert web_login(harness.client, "root", PASSWORD).status_code == 303
    admin = harness.client.get("/admin").text
    assert "not installed: run <code>semantic3d admin add-challenge reduced-8" in admin
    submit = harness.client.get("/submit").text
    assert f"reduced-8</strong>: {NOT_INSTALLED}" in submit
    assert '<option value="reduced-8"' not in submit
    csrf = form_csrf(admin)
    refused = harness.client.post(
        "/admin/challenges/reduced-8/open", data={"is_open": "1", "csrf_token": csrf}
    )
    assert refused.status_code == 400 and NOT_INSTALLED in refused.text


def test_installing_the_ground_truth_completes_and_opens_the_listed_challenge(
    harness: Harness, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    spec = load_challenge("reduced-8", ground_truth_root=None)
    folder = tmp_path / "reduced-8-labels"
    folder.mkdir()
    for scan in spec.scans:
        (folder / f"{scan.name}.labels").write_text("1\n")
    # Counting 80 million lines is the slow test's job; here the protocol's counts stand in.
    monkeypatch.setattr(
        challenges_module, "count_ground_truth_lines", lambda scan: int(scan.n_points)
    )
    with harness.state.factory() as session:
        listed_id = get_challenge(session, "reduced-8").id

    row = install_challenge(harness.state.factory, harness.settings, "reduced-8", folder)

    assert row.id == listed_id and row.ground_truth_installed and row.is_open
    with harness.state.factory() as session:
        stored = get_challenge(session, "reduced-8")
        assert (stored.id, stored.n_scans, stored.is_open) == (listed_id, 4, True)
        assert stored.ground_truth_installed and stored.protocol_version == "1"
        assert len(session.scalars(select(ChallengeRecord)).all()) == 3
    listed = harness.client.get("/api/challenges/reduced-8").json()
    assert listed["status"] == "open" and listed["accepts_submissions"]
    page = harness.client.get("/challenges/reduced-8").text
    assert "Submit to this challenge" in page and 'id="not-installed"' not in page
    assert page.count('<tr class="tag-') == len(BOARD_ORDER["reduced-8"])
    with pytest.raises(InvalidInputError, match="already installed"):
        install_challenge(harness.state.factory, harness.settings, "reduced-8", folder)


def test_participants_are_ranked_and_references_sorted_in_unranked(harness: Harness) -> None:
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
    board = harness.client.get("/api/challenges/toy/leaderboard").json()
    assert [row["rank"] for row in board["entries"]] == [1]

    def entry(
        method: str, mean_iou: float | None, *, rank: int | None, oa: float | None = None
    ) -> LeaderboardEntry:
        return LeaderboardEntry(
            rank=rank,
            submission_id=rank,
            method=method,
            submitted_by="x",
            mean_iou=mean_iou,
            overall_accuracy=oa,
            iou=(None,) * len(CLASSES),
            runtime_s=None,
            hardware=None,
            submitted_at=datetime.now(UTC) if rank else None,
            paper_url="",
            code_url="",
            reference=rank is None,
        )

    participants = [
        entry("a", 0.7, rank=1, oa=0.95),
        entry("b", 0.5, rank=2, oa=0.90),
        entry("c", 0.4, rank=3, oa=0.80),
    ]
    references = [entry("r-none", None, rank=None), entry("r1", 0.5, rank=None)]
    references.append(entry("r2", 0.9, rank=None))
    # No mean IoU but an overall accuracy: sorted by that, not sent to the bottom.
    references.append(entry("r-oa", None, rank=None, oa=0.85))
    merged = merged_rows(participants, references)
    assert [row.method for row in merged] == ["r2", "a", "b", "r1", "r-oa", "c", "r-none"]
    assert [row.rank for row in merged if not row.reference] == [1, 2, 3]


def test_the_shipped_reference_file_is_consistent() -> None:
    shipped = reference_results()
    assert shipped.version >= 2
    for name, methods in PAPER_ROWS.items():
        paper = [row for row in shipped.for_challenge(name) if row.source.key == "hackel2017"]
        assert [row.method for row in paper] == methods
    assert shipped.for_challenge("custom") == ()
    assert shipped.benchmark_source.year == 2017
    for row in shipped.results:
        assert len(row.iou) == len(row.iou_notes) == len(CLASSES)
        assert all(v is None or 0 <= v <= 1 for v in (row.mean_iou, row.overall_accuracy, *row.iou))
        assert row.source.url.startswith("https://") and row.source.year >= 2017
        assert row.tag == ("paper-baseline" if row.method in PAPER_BASELINES else "published")
        # Every row says where its values come from: the paper's table, or a note.
        assert row.table or row.note, row.method
        known = [v for v in row.iou if v is not None]
        if row.mean_iou is not None and len(known) == len(CLASSES):  # the loader's check
            assert abs(math.fsum(known) / len(known) - row.mean_iou) <= 0.0006, row.method
    assert {row.method for row in shipped.results if any(row.iou_notes)} == {"TML-PC", "TML-PCR"}


_SOURCE = """
version = 2
benchmark_source = "p"
[sources.p]
citation = "A paper"
url = "https://example.org/paper"
label = "paper"
year = 2020
"""
_ROW = 'tag = "published"\nsource = "p"\n'


@pytest.mark.parametrize(
    ("result", "match"),
    [
        ('challenge = "semantic-8"\nmethod = "X"\ncolour = 1', "unknown key"),
        ('challenge = "mine"\nmethod = "X"', "expected one of semantic-8, reduced-8"),
        ('challenge = "semantic-8"\nmethod = "X"\nmean_iou = 43.7', "expected a fraction 0..1"),
        ('challenge = "semantic-8"\nmethod = "X"\nruntime_s = -1', "runtime_s: expected seconds"),
        ('challenge = "semantic-8"\nmethod = "X"\niou = { trees = 0.5 }', "unknown class name"),
        (
            'challenge = "semantic-8"\nmethod = "X"\nmean_iou = 0.5\niou = { '
            + ", ".join(f'"{c.name}" = 0.4' for c in CLASSES)
            + " }",
            "per-class IoU average 0.4000",
        ),
        (
            'challenge = "semantic-8"\nmethod = "X"\ntag = "verified"\nsource = "p"',
            "tag: expected one of paper-baseline, published, found 'verified'",
        ),
        (
            'challenge = "semantic-8"\nmethod = "X"\ntag = "published"\nsource = "q"',
            "source: expected one of p, found 'q'",
        ),
        (
            'challenge = "semantic-8"\nmethod = "X"\npaper_url = "http://x.org"',
            "paper_url: expected an https:// address",
        ),
    ],
)
def test_a_bad_reference_file_is_refused_with_where_and_what(
    tmp_path: Path, result: str, match: str
) -> None:
    path = tmp_path / "refs.toml"
    row = result if "tag =" in result else _ROW + result
    path.write_text(_SOURCE + "[[results]]\n" + row + "\n")
    with pytest.raises(DataFormatError, match=match):
        read_reference_results(path)


def test_two_rows_of_a_challenge_need_two_names_and_a_source_needs_a_year(
    tmp_path: Path,
) -> None:
    path = tmp_path / "refs.toml"
    rows = "".join(
        f'[[results]]\nchallenge = "reduced-8"\nmethod = "{name}"\n{_ROW}'
        for name in ("X Y", "x-y")
    )
    path.write_text(_SOURCE + rows)
    with pytest.raises(DataFormatError, match="two rows of reduced-8 named 'x-y'"):
        read_reference_results(path)
    path.write_text(_SOURCE.replace("year = 2020\n", ""))
    with pytest.raises(DataFormatError, match=r"\[sources.p\]: expected .* a year"):
        read_reference_results(path)


def test_per_class_values_and_their_mean_are_read_in_class_order(tmp_path: Path) -> None:
    values = [0.9, 0.7, 0.5, 0.3, 0.8, 0.2, 0.1, 0.6]
    path = tmp_path / "refs.toml"
    iou = ", ".join(f'"{c.name}" = {v}' for c, v in zip(CLASSES, values, strict=True))
    mean = round(math.fsum(values) / len(values), 3)
    path.write_text(
        _SOURCE
        + f'[[results]]\nchallenge = "reduced-8"\nmethod = "X"\n{_ROW}mean_iou = {mean}\n'
        + f"iou = {{ {iou} }}\n"
    )
    (row,) = read_reference_results(path).for_challenge("reduced-8")
    assert row.iou == tuple(values) and row.mean_iou == mean


def test_upgrading_keeps_an_installed_benchmark_challenge_and_lists_the_other(
    tmp_path: Path,
) -> None:
    from alembic import command
    from alembic.config import Config

    from semantic3d.server.db import MIGRATIONS_DIR

    settings = make_settings(tmp_path / "data")
    settings.prepare_data_dir()
    engine = create_db_engine(settings)
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    with engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, "0002")
        connection.execute(
            text(
                "INSERT INTO challenges (name, kind, title, description, protocol_version, "
                "n_scans, n_points, scan_points_json, is_open, created_at) VALUES "
                "('reduced-8', 'reduced-8', 'Reduced', '', '1', 4, 10, '{}', 0, "
                "'2026-01-01 00:00:00')"
            )
        )
    run_migrations(engine)
    factory = create_session_factory(engine)
    with factory() as session:
        rows = {row.name: row for row in session.scalars(select(ChallengeRecord))}
    engine.dispose()
    assert set(rows) == {"reduced-8", "semantic-8"}
    assert rows["reduced-8"].ground_truth_installed and rows["reduced-8"].title == "Reduced"
    assert rows["reduced-8"].is_open is False  # an admin's choice is kept
    assert not rows["semantic-8"].ground_truth_installed and not rows["semantic-8"].is_open


def test_a_fresh_server_says_why_nothing_can_be_submitted_yet(tmp_path: Path) -> None:
    from fastapi.testclient import TestClient

    from semantic3d.server.app import create_app
    from semantic3d.server.services.accounts import create_user

    app = create_app(make_settings(tmp_path / "data"))
    create_user(app.state.server.factory, "alice", PASSWORD)
    with TestClient(app) as client:
        assert web_login(client, "alice", PASSWORD).status_code == 303
        page = client.get("/submit").text
    assert "No challenge is open for submissions." in page
    assert page.count(f"</strong>: {NOT_INSTALLED}</li>") == 2
