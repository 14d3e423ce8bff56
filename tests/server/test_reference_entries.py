"""The benchmark's own challenges on a fresh server, and the paper's reference results."""

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


def test_the_boards_show_the_papers_rows_as_unranked_references(harness: Harness) -> None:
    for name, methods in PAPER_ROWS.items():
        board = harness.client.get(f"/api/challenges/{name}/leaderboard").json()
        assert board["entries"] == []
        assert [row["method"] for row in board["references"]] == methods
        assert all(row["reference"] and row["rank"] is None for row in board["references"])
        assert "1704.03847" in board["reference_source"]["url"]
        assert "Hackel" in board["reference_source"]["citation"]
    deep_net = next(
        row
        for row in harness.client.get("/api/challenges/reduced-8/leaderboard").json()["references"]
        if row["method"] == "DeepNet"
    )
    assert (deep_net["mean_iou"], deep_net["overall_accuracy"]) == (0.437, 0.772)
    assert deep_net["runtime_s"] == 64_800

    page = harness.client.get("/challenges/reduced-8").text
    assert page.count('class="badge ref"') == len(PAPER_ROWS["reduced-8"]) + 1  # + the note
    assert 'id="not-installed"' in page and NOT_INSTALLED in page
    assert "ground-truth" not in page  # no data paths or admin commands on public pages
    assert "Submit to this challenge" not in page
    assert "43.7" in page and "77.2" in page and "18.0 h" in page

    # A custom challenge has no reference rows.
    toy = harness.client.get("/api/challenges/toy/leaderboard").json()
    assert toy["references"] == [] and toy["reference_source"] is None
    assert "badge ref" not in harness.client.get("/challenges/toy").text


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
    assert page.count('class="badge ref"') == len(PAPER_ROWS["reduced-8"]) + 1
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

    def entry(method: str, mean_iou: float | None, *, rank: int | None) -> LeaderboardEntry:
        return LeaderboardEntry(
            rank=rank,
            submission_id=rank,
            method=method,
            submitted_by="x",
            mean_iou=mean_iou,
            overall_accuracy=None,
            iou=(None,) * len(CLASSES),
            runtime_s=None,
            hardware=None,
            submitted_at=datetime.now(UTC) if rank else None,
            paper_url="",
            code_url="",
            reference=rank is None,
        )

    participants = [entry("a", 0.7, rank=1), entry("b", 0.5, rank=2), entry("c", 0.4, rank=3)]
    references = [entry("r-none", None, rank=None), entry("r1", 0.5, rank=None)]
    references.append(entry("r2", 0.9, rank=None))
    merged = merged_rows(participants, references)
    assert [row.method for row in merged] == ["r2", "a", "b", "r1", "c", "r-none"]
    assert [row.rank for row in merged if not row.reference] == [1, 2, 3]


def test_the_shipped_reference_file_is_consistent() -> None:
    shipped = reference_results()
    assert shipped.version >= 1
    for name, methods in PAPER_ROWS.items():
        assert [row.method for row in shipped.for_challenge(name)] == methods
    assert shipped.for_challenge("custom") == ()
    by_method = {row.method: row for row in shipped.results}
    # The values checked against the paper (the rest stays empty until checked).
    assert by_method["DeepNet"].mean_iou == 0.437
    assert by_method["DeepNet"].overall_accuracy == 0.772
    assert by_method["DeepNet"].runtime_s == 64_800
    assert by_method["TML-PC"].mean_iou == 0.391
    assert (by_method["TML-PCR"].mean_iou, by_method["TML-PCR"].overall_accuracy) == (0.384, 0.74)
    for row in shipped.results:
        assert len(row.iou) == len(CLASSES)
        assert all(v is None or 0 <= v <= 1 for v in (row.mean_iou, row.overall_accuracy, *row.iou))


_SOURCE = """
version = 1
[source]
citation = "A paper"
url = "https://example.org/paper"
label = "paper"
"""


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
    ],
)
def test_a_bad_reference_file_is_refused_with_where_and_what(
    tmp_path: Path, result: str, match: str
) -> None:
    path = tmp_path / "refs.toml"
    path.write_text(_SOURCE + "[[results]]\n" + result + "\n")
    with pytest.raises(DataFormatError, match=match):
        read_reference_results(path)


def test_per_class_values_and_their_mean_are_read_in_class_order(tmp_path: Path) -> None:
    values = [0.9, 0.7, 0.5, 0.3, 0.8, 0.2, 0.1, 0.6]
    path = tmp_path / "refs.toml"
    iou = ", ".join(f'"{c.name}" = {v}' for c, v in zip(CLASSES, values, strict=True))
    mean = round(math.fsum(values) / len(values), 3)
    path.write_text(
        _SOURCE
        + f'[[results]]\nchallenge = "reduced-8"\nmethod = "X"\nmean_iou = {mean}\n'
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
