"""``semantic3d demo --serve`` support: the demo's prediction scored and published by the server."""

from __future__ import annotations

from pathlib import Path

from semantic3d.evaluation import MethodInfo, custom_challenge, evaluate_submission
from semantic3d.io.labels import write_labels
from semantic3d.server.db import create_db_engine, create_session_factory, run_migrations
from semantic3d.server.demo import prepare_demo
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

    again = prepare_demo(
        factory, settings, ground_truth=ground_truth_dir, predictions=predictions, method=method
    )
    assert again.password is None and again.submission_id != demo.submission_id
    assert not list(settings.uploads_dir.iterdir())
