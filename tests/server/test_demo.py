"""``semantic3d demo --serve`` support: the demo's prediction scored and published by the server."""

from __future__ import annotations

from pathlib import Path

from semantic3d.evaluation import MethodInfo, custom_challenge, evaluate_submission
from semantic3d.io.labels import write_labels
from semantic3d.server.db import create_db_engine, create_session_factory, run_migrations
from semantic3d.server.demo import prepare_demo
from semantic3d.server.models import Submission
from semantic3d.server.services.leaderboard import LeaderboardCache

from .conftest import ground_truth_arrays, make_settings, noisy_predictions


def test_prepare_demo_publishes_the_same_score(tmp_path: Path, ground_truth_dir: Path) -> None:
    predictions = tmp_path / "predictions"
    predictions.mkdir()
    for name, values in noisy_predictions(ground_truth_arrays(), 0.8).items():
        write_labels(predictions / f"{name}.labels", [values])
    method = MethodInfo("covariance forest", runtime_s=12.0, hardware="laptop")
    expected = evaluate_submission(
        predictions, challenge=custom_challenge(ground_truth_dir), method=method
    )

    settings = make_settings(tmp_path / "server-data")
    engine = create_db_engine(settings)
    run_migrations(engine)
    factory = create_session_factory(engine)
    demo = prepare_demo(
        factory, settings, ground_truth=ground_truth_dir, predictions=predictions, method=method
    )
    assert demo.mean_iou == expected.mean_iou
    assert demo.password and demo.token and demo.token.startswith("s3d_")
    challenge, entries = LeaderboardCache(factory, 0).board("demo")
    assert challenge.title.startswith("Demo")
    assert [(e.method, e.mean_iou) for e in entries] == [("covariance forest", expected.mean_iou)]

    # Running the demo again rewrites the same predictions (new files, new times): the
    # board keeps its one row, the same submission.
    for name, values in noisy_predictions(ground_truth_arrays(), 0.8).items():
        write_labels(predictions / f"{name}.labels", [values])
    again = prepare_demo(
        factory, settings, ground_truth=ground_truth_dir, predictions=predictions, method=method
    )
    assert again.password is None and again.submission_id == demo.submission_id
    _, entries = LeaderboardCache(factory, 0).board("demo")
    assert [e.submission_id for e in entries] == [demo.submission_id]

    # New predictions: a new submission, shown instead of the old one (which is kept).
    for name, values in noisy_predictions(ground_truth_arrays(), 0.6, seed=3).items():
        write_labels(predictions / f"{name}.labels", [values])
    newer = prepare_demo(
        factory, settings, ground_truth=ground_truth_dir, predictions=predictions, method=method
    )
    assert newer.submission_id != demo.submission_id
    _, entries = LeaderboardCache(factory, 0).board("demo")
    assert [e.submission_id for e in entries] == [newer.submission_id]
    with factory() as session:
        assert session.get_one(Submission, demo.submission_id).published is False
    assert not list(settings.uploads_dir.iterdir())


def test_the_demo_board_renders_its_text_counts_and_times_for_people(
    tmp_path: Path, ground_truth_dir: Path
) -> None:
    from fastapi.testclient import TestClient

    from semantic3d.server.app import create_app

    predictions = tmp_path / "predictions"
    predictions.mkdir()
    for name, values in noisy_predictions(ground_truth_arrays(), 0.8).items():
        write_labels(predictions / f"{name}.labels", [values])
    settings = make_settings(tmp_path / "server-data")
    app = create_app(settings)
    method = MethodInfo("covariance forest", runtime_s=16.0136, hardware="laptop")
    prepare_demo(
        app.state.server.factory,
        settings,
        ground_truth=ground_truth_dir,
        predictions=predictions,
        method=method,
    )
    with TestClient(app) as client:
        page = client.get("/challenges/demo").text
        index = client.get("/").text
    assert "`" not in page and "<code>semantic3d demo</code>" in page
    assert "<code>semantic3d demo</code>" in index
    n_scans = len(list(ground_truth_dir.glob("*.labels")))
    assert f"{n_scans} scan{'' if n_scans == 1 else 's'}," in page
    assert "1 scans" not in page
    assert ">16 s<" in page and "16.0136 s" not in page
