"""Prediction of whole scans: tiled equals in memory, input order, sidecar."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from semantic3d.baselines.covariance.config import PredictionConfig
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.baselines.covariance.predict import describe_hardware, predict_cloud, predict_scan
from semantic3d.baselines.covariance.training import (
    build_training_set,
    find_labelled_scans,
    fit_model,
)
from semantic3d.core.errors import GroundTruthOutputError, OutputExistsError
from semantic3d.core.threads import thread_budget
from semantic3d.core.timeline import Span, recording
from semantic3d.features import FeatureConfig
from semantic3d.io.ascii import read_ascii_points
from semantic3d.io.labels import read_labels
from tests.baselines.conftest import SMALL_CONFIG


@pytest.fixture(scope="module", params=[False, True], ids=["voxel", "per_point"])
def model(request: pytest.FixtureRequest, scene_dir: Path) -> CovarianceModel:
    features = dataclasses.replace(SMALL_CONFIG.features, per_point=request.param)
    config = dataclasses.replace(SMALL_CONFIG, features=features)
    scans = find_labelled_scans(scene_dir, names=["train_a"])
    return fit_model(build_training_set(scans, config=config), config=config)


def _with_prediction(model: CovarianceModel, **kwargs: object) -> CovarianceModel:
    prediction = dataclasses.replace(model.config.prediction, **kwargs)
    return dataclasses.replace(
        model, config=dataclasses.replace(model.config, prediction=prediction)
    )


def test_tiled_prediction_equals_in_memory_prediction(
    model: CovarianceModel, scene_dir: Path, tmp_path: Path
) -> None:
    scan = scene_dir / "test.txt"
    whole = predict_scan(
        _with_prediction(model, max_points_in_memory=10**9), scan, out_path=tmp_path / "a.labels"
    )
    tiled = predict_scan(
        _with_prediction(model, max_points_in_memory=0, tile_size_m=6.4),
        scan,
        out_path=tmp_path / "b.labels",
        workdir=tmp_path,
    )
    assert not whole.tiled and tiled.tiled
    expected = read_labels(whole.labels_path)
    assert expected.size == whole.n_points == tiled.n_points
    np.testing.assert_array_equal(read_labels(tiled.labels_path), expected)
    # the labels follow the input's point order: same as labelling the cloud in memory
    np.testing.assert_array_equal(predict_cloud(model, read_ascii_points(scan)), expected)
    assert not any(p.name.startswith("s3d-") for p in tmp_path.iterdir())  # scratch removed


def test_a_tiled_prediction_marks_its_steps_on_a_timeline_and_labels_the_same(
    model: CovarianceModel, scene_dir: Path, tmp_path: Path
) -> None:
    tiled = _with_prediction(model, max_points_in_memory=0, tile_size_m=6.4)
    context = dataclasses.replace(tiled.config.context, max_graph_nodes=200)
    tiled = dataclasses.replace(tiled, config=dataclasses.replace(tiled.config, context=context))
    scan = scene_dir / "test.txt"
    plain = predict_scan(tiled, scan, out_path=tmp_path / "a.labels", workdir=tmp_path)
    with recording() as timeline:
        marked = predict_scan(tiled, scan, out_path=tmp_path / "b.labels", workdir=tmp_path)
    np.testing.assert_array_equal(read_labels(marked.labels_path), read_labels(plain.labels_path))
    spans = timeline.spans
    by_number = {s.number: s for s in spans}

    def tile_of(step: Span) -> Span | None:
        while step.parent != -1:
            step = by_number[step.parent]
        return step if step.name == "tile" else None

    (spill,) = timeline.named("spill")
    tiles = timeline.named("tile")
    assert spill.attrs["points"] == marked.n_points and spill.attrs["tiles"] == len(tiles) > 1
    assert sum(t.attrs["points"] for t in tiles) == marked.n_points
    assert len(timeline.named("pyramid")) == len(tiles)
    assert all(spill.end_s <= p.start_s for p in timeline.named("pyramid"))
    for step in ("features", "forest", "cut"):
        inside = [s for s in timeline.named(step) if tile_of(s) is not None]
        assert len(inside) == len(tiles), step  # each tile's own, on its thread
    squares = timeline.named("cut square")
    assert squares and all(tile_of(s) is not None for s in squares)
    for step in timeline.named("features") + timeline.named("forest"):
        assert 1 <= step.attrs["threads"] <= thread_budget(), step
    for cut in timeline.named("squares"):  # the graphs cut in squares, on the tile's threads
        assert cut.attrs["groups"] > 1 and 1 <= cut.attrs["threads"] <= thread_budget()
        assert tile_of(cut) is not None
    assert max(s.attrs["rows"] for s in squares) <= 200  # the tiles' graphs cut in squares
    (written,) = timeline.named("write labels")
    assert written.attrs["points"] == marked.n_points
    assert max(t.end_s for t in tiles) <= written.start_s
    assert sum(s.attrs["points"] for s in timeline.named("put labels")) == marked.n_points


def test_sidecar_records_time_and_hardware(
    model: CovarianceModel, scene_dir: Path, tmp_path: Path
) -> None:
    run = predict_scan(model, scene_dir / "test.txt", out_path=tmp_path / "t.labels")
    sidecar = json.loads((tmp_path / "t.labels.json").read_text())
    assert sidecar["n_points"] == run.n_points > 0
    assert sidecar["runtime_s"] == pytest.approx(run.runtime_s) and run.runtime_s > 0
    assert sidecar["hardware"]["logical_cores"] >= 1
    assert sidecar["hardware"]["ram_bytes"] > 2**28
    assert sidecar["training_scans"] == ["train_a"]
    assert describe_hardware().describe().count("cores") == 1


def test_an_existing_output_is_refused_before_any_work(
    model: CovarianceModel, scene_dir: Path, tmp_path: Path
) -> None:
    truth = scene_dir / "test.labels"
    before = truth.read_bytes()
    with pytest.raises(GroundTruthOutputError, match=r"test\.labels: is the ground truth"):
        predict_scan(model, scene_dir / "test.txt", out_path=truth)
    assert truth.read_bytes() == before
    (tmp_path / "p.labels").write_bytes(b"1\n")
    with pytest.raises(OutputExistsError, match=r"p\.labels: already exists.*overwrite=True"):
        predict_scan(model, scene_dir / "test.txt", out_path=tmp_path / "p.labels")
    (tmp_path / "p.labels").unlink()
    (tmp_path / "p.labels.json").write_text("{}")
    with pytest.raises(OutputExistsError, match=r"p\.labels\.json: already exists"):
        predict_scan(model, scene_dir / "test.txt", out_path=tmp_path / "p.labels")
    assert not (tmp_path / "p.labels").exists()
    run = predict_scan(
        model, scene_dir / "test.txt", out_path=tmp_path / "p.labels", overwrite=True
    )
    assert json.loads((tmp_path / "p.labels.json").read_text())["n_points"] == run.n_points


def test_a_model_is_tied_to_its_feature_columns(model: CovarianceModel) -> None:
    with pytest.raises(ValueError, match=r"feature rows: expected \(n, "):
        model.predict_rows(np.zeros((3, FeatureConfig(n_levels=2).n_features), np.float32))
    assert isinstance(model.config.prediction, PredictionConfig)


def test_the_forest_run_on_rows_as_they_are_made_labels_as_on_the_whole_table(
    model: CovarianceModel, scene_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Prediction runs the forest on each tile's rows a block at a time as they are made
    (its table never whole); per tile, its labels, context step and all, are those of
    ``predict_rows`` on the tile's whole table."""
    import semantic3d.features.multiscale as multiscale
    from semantic3d.baselines.covariance.context import row_centroids
    from semantic3d.features.tiling import TiledScan

    monkeypatch.setattr(multiscale, "ROW_BLOCK", 37)  # many blocks a tile
    points = read_ascii_points(scene_dir / "test.txt")
    with TiledScan(
        [points], config=model.config.features, tile_size_m=6.4, workdir=tmp_path
    ) as scan:
        assert len(scan.tiles) > 2
        for tile in scan.tiles:
            whole = scan.tile_features(tile)
            mapped = scan.tile_features(tile, row_map=model.row_probabilities)
            assert whole is not None and mapped is not None
            assert mapped.table.mapped is not None and mapped.table.values.shape[1] == 0
            graph: dict[str, np.ndarray | None] = {"neighbours": whole.table.neighbours}
            if model.needs_row_positions(whole.table):
                graph["row_xyz"] = row_centroids(
                    whole.xyz.astype(np.float32), whole.table.point_row, whole.table.n_rows
                )
            expected = model.predict_rows(whole.table.values, **graph)
            np.testing.assert_array_equal(
                model.label_probabilities(mapped.table.mapped, **graph), expected
            )
            np.testing.assert_array_equal(
                mapped.table.mapped, model.row_probabilities(whole.table.values)
            )
