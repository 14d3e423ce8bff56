"""The context step in the covariance baseline: configuration, prediction, model file."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from semantic3d.baselines.covariance.config import (
    ConfigError,
    ContextConfig,
    CovarianceConfig,
    load_config,
    preset_config,
)
from semantic3d.baselines.covariance.context import (
    knn_edges,
    potts_energy,
    row_centroids,
    unary_costs,
)
from semantic3d.baselines.covariance.model import CovarianceModel, point_tiles
from semantic3d.baselines.covariance.persistence import load_model, read_model_header, save_model
from semantic3d.baselines.covariance.predict import predict_cloud, predict_scan
from semantic3d.baselines.covariance.training import (
    build_training_set,
    find_labelled_scans,
    fit_model,
)
from semantic3d.core import PointCloud
from semantic3d.features import compute_multiscale_features
from semantic3d.features.pyramid import grid_origin
from semantic3d.io.ascii import read_ascii_points
from semantic3d.io.labels import read_labels
from semantic3d.metrics import ConfusionMatrix
from tests.baselines.conftest import SMALL_CONFIG, write_scan
from tests.baselines.scene import make_street_scene


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("context")
    write_scan(folder, "train", make_street_scene(20, size_m=16.0))
    write_scan(folder, "test", make_street_scene(21, size_m=16.0))
    return folder


@pytest.fixture(scope="module")
def model(scenes: Path) -> CovarianceModel:
    config = dataclasses.replace(SMALL_CONFIG, context=ContextConfig(potts_weight=2.0))
    scans = find_labelled_scans(scenes, names=["train"])
    return fit_model(build_training_set(scans, config=config), config=config)


def _with(model: CovarianceModel, **changes: object) -> CovarianceModel:
    return dataclasses.replace(model, config=dataclasses.replace(model.config, **changes))


def _shuffled(points: PointCloud, *, seed: int) -> tuple[np.ndarray, PointCloud]:
    """The points in a random order, the first kept first (it anchors the grids)."""
    order = np.concatenate([[0], 1 + np.random.default_rng(seed).permutation(points.n_points - 1)])
    labels = None if points.labels is None else points.labels[order]
    shuffled = PointCloud(
        xyz=points.xyz[order],
        intensity=points.intensity[order],
        rgb=points.rgb[order],
        labels=labels,
    )
    return order, shuffled


def _miou(truth: np.ndarray, predicted: np.ndarray) -> float:
    matrix = ConfusionMatrix()
    matrix.update(truth, predicted)
    return float(matrix.compute_scores().mean_iou)


def test_the_context_step_is_on_by_default_and_off_in_the_paper_preset() -> None:
    assert CovarianceConfig().context.enabled
    assert not preset_config("paper").context.enabled
    assert ContextConfig(potts_weight=2.0).enabled


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("[context]\npotts_weight = -1.0\n", r"\[context\] potts_weight: expected a number >= 0"),
        ("[context]\nn_neighbours = 0\n", r"\[context\] n_neighbours: expected a positive"),
        ("[context]\nmax_sweeps = 0\n", r"\[context\] max_sweeps: expected a positive"),
        ("[context]\nweight = 1.0\n", r"weight"),
        (
            "[context]\nmax_graph_nodes = -1\n",
            r"\[context\] max_graph_nodes: expected an integer >= 0, found -1",
        ),
    ],
)
def test_a_bad_context_section_is_rejected(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(path)


def test_a_context_section_is_read(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[context]\npotts_weight = 0.5\nmax_sweeps = 2\nmax_graph_nodes = 0\n")
    assert load_config(path).context == ContextConfig(
        potts_weight=0.5, max_sweeps=2, max_graph_nodes=0
    )


def test_a_model_saved_before_the_graph_cap_still_cuts_whole_tiles() -> None:
    """A context section pickled with three fields unpickles with ``max_graph_nodes = 0``
    (whole tiles: its labels as when it was saved); a current one keeps its value."""
    import pickle

    older = ContextConfig.__new__(ContextConfig)
    older.__setstate__([2.0, 8, 1])
    assert older == ContextConfig(potts_weight=2.0, max_graph_nodes=0)
    current = ContextConfig(potts_weight=2.0, max_graph_nodes=77)
    assert pickle.loads(pickle.dumps(current)) == current


def test_context_lowers_the_energy_and_keeps_labels_in_input_order(
    model: CovarianceModel, scenes: Path, tmp_path: Path
) -> None:
    cloud = find_labelled_scans(scenes, names=["test"])[0]  # tiles of 6.4 m (SMALL_CONFIG)
    points = read_ascii_points(cloud.points_path, labels_path=cloud.labels_path)
    assert points.labels is not None
    with_context = predict_cloud(model, points)
    plain = predict_cloud(_with(model, context=ContextConfig(potts_weight=0.0)), points)
    assert not np.array_equal(with_context, plain)
    assert _miou(points.labels, with_context) >= _miou(points.labels, plain) - 0.01

    # The Potts energy of the rows' labels falls (over the edges inside each tile).
    table = compute_multiscale_features(points, config=model.config.features)
    proba = model.classifier.predict_proba(table.values)
    row_xyz = row_centroids(
        (points.xyz - points.xyz[0]).astype(np.float32), table.point_row, table.n_rows
    )
    origin = grid_origin(
        points.xyz[0], coarsest_voxel_size_m=model.config.features.coarsest_voxel_size_m
    )
    row_tile = np.zeros(table.n_rows, np.int64)
    row_tile[table.point_row] = point_tiles(points.xyz, origin=origin, config=model.config)
    assert np.unique(row_tile).size > 1
    edges = knn_edges(row_xyz, k=model.config.context.n_neighbours)
    edges = edges[row_tile[edges[:, 0]] == row_tile[edges[:, 1]]]
    classes = list(model.classifier.classes_)
    row_labels = np.zeros(table.n_rows, np.uint8)
    row_labels[table.point_row] = with_context
    columns = np.array([classes.index(v) for v in row_labels])
    unary, weight = unary_costs(proba), model.config.context.potts_weight
    assert potts_energy(unary, edges, columns, weight=weight) < potts_energy(
        unary, edges, proba.argmax(axis=1), weight=weight
    )

    # Shuffled input (the first point kept first: it anchors the grids): every point
    # keeps its label, so labels follow the input order.
    order, shuffled = _shuffled(points, seed=0)
    np.testing.assert_array_equal(predict_cloud(model, shuffled), with_context[order])

    # Streamed and tiled prediction give the in-memory labels exactly.
    whole = predict_scan(
        _with(model, prediction=dataclasses.replace(model.config.prediction, chunk_size=5_000)),
        cloud.points_path,
        out_path=tmp_path / "whole.labels",
    )
    tiled = predict_scan(
        _with(
            model,
            prediction=dataclasses.replace(
                model.config.prediction, max_points_in_memory=0, tile_size_m=6.4
            ),
        ),
        cloud.points_path,
        out_path=tmp_path / "tiled.labels",
        workdir=tmp_path,
    )
    assert tiled.tiled and not whole.tiled
    np.testing.assert_array_equal(read_labels(whole.labels_path), with_context)
    np.testing.assert_array_equal(read_labels(tiled.labels_path), with_context)


def test_the_context_settings_survive_the_model_file(
    model: CovarianceModel, scenes: Path, tmp_path: Path
) -> None:
    path = save_model(model, tmp_path / "m.s3d")
    assert read_model_header(path)["config"]["context"] == {
        "potts_weight": 2.0,
        "n_neighbours": 8,
        "max_sweeps": 1,
        "max_graph_nodes": 65536,
    }
    loaded = load_model(path)
    assert loaded.config.context == model.config.context
    points = read_ascii_points(scenes / "test.txt")
    np.testing.assert_array_equal(predict_cloud(loaded, points), predict_cloud(model, points))


def test_a_dense_tile_cut_in_squares_gives_the_same_labels_however_it_is_read(
    model: CovarianceModel, scenes: Path, tmp_path: Path
) -> None:
    """With a cap below the test scan's tiles, their graphs are cut in squares: labels
    change a little, and stay the same in memory, streamed, tiled, on shuffled input and
    on any number of threads."""
    from semantic3d.core.threads import thread_limit

    cloud = find_labelled_scans(scenes, names=["test"])[0]
    points = read_ascii_points(cloud.points_path, labels_path=cloud.labels_path)
    assert points.labels is not None
    capped = _with(model, context=dataclasses.replace(model.config.context, max_graph_nodes=300))
    whole_tiles = predict_cloud(_with(model, context=model.config.context), points)
    squares = predict_cloud(capped, points)
    changed = np.mean(squares != whole_tiles)
    assert 0 < changed < 0.05
    assert _miou(points.labels, squares) >= _miou(points.labels, whole_tiles) - 0.02

    order, shuffled = _shuffled(points, seed=1)
    np.testing.assert_array_equal(predict_cloud(capped, shuffled), squares[order])
    with thread_limit(1):
        np.testing.assert_array_equal(predict_cloud(capped, points), squares)
    tiled = predict_scan(
        _with(
            capped,
            prediction=dataclasses.replace(
                model.config.prediction, max_points_in_memory=0, chunk_size=5_000
            ),
        ),
        cloud.points_path,
        out_path=tmp_path / "tiled.labels",
        workdir=tmp_path,
    )
    assert tiled.tiled
    np.testing.assert_array_equal(read_labels(tiled.labels_path), squares)


def test_rows_take_the_tile_and_square_of_their_last_point(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Rows placed on every thread get what numpy's assignment gives (the last of a row's
    points decides), also where a row's points disagree."""
    from semantic3d.baselines.covariance.model import _PositionFile

    rng = np.random.default_rng(3)
    n_points, n_rows = 50_000, 4_000
    tiles = rng.integers(0, 5, n_points).astype(np.int64)
    cells = rng.integers(0, 4096, n_points).astype(np.uint16)
    (tmp_path / "xyz.f32").write_bytes(np.zeros((n_points, 3), np.float32).tobytes())
    (tmp_path / "tiles.i64").write_bytes(tiles.tobytes())
    (tmp_path / "cells.u16").write_bytes(cells.tobytes())
    positions = _PositionFile(tmp_path, None)  # type: ignore[arg-type]
    positions._complete = True
    picked = np.sort(rng.choice(n_points, 30_000, replace=False))
    point_row = rng.integers(0, n_rows, picked.size)
    for agree in (False, True):
        if agree:  # every row's points share its tile and square
            source = rng.integers(0, n_points, n_rows)
            tiles[picked] = tiles[source[point_row]]
            cells[picked] = cells[source[point_row]]
            (tmp_path / "tiles.i64").write_bytes(tiles.tobytes())
            (tmp_path / "cells.u16").write_bytes(cells.tobytes())
        row_tile, row_cell = positions.row_places(picked, point_row, n_rows)
        expected_tile = np.zeros(n_rows, np.int64)
        expected_tile[point_row] = tiles[picked]
        expected_cell = np.zeros(n_rows, np.uint16)
        expected_cell[point_row] = cells[picked]
        np.testing.assert_array_equal(row_tile, expected_tile)
        np.testing.assert_array_equal(row_cell, expected_cell)


@pytest.mark.parametrize("threads", [1, 2, 8])
@pytest.mark.parametrize("n_rows", [1, 7, 3_000])
def test_a_rows_last_point_is_found_on_any_number_of_threads(threads: int, n_rows: int) -> None:
    """Passes race only to raise a row's point: the result is the largest point of each
    row (-1 without points), what a sequential pass gives, for any threads."""
    from semantic3d.baselines.covariance.context import last_points
    from semantic3d.core.threads import thread_limit

    rng = np.random.default_rng(n_rows)
    point_row = rng.integers(0, n_rows, 200_000)
    point_row[-5:] = 0  # the last points in one row
    expected = np.full(n_rows + 2, -1, np.int64)
    expected[point_row] = np.arange(point_row.size)
    with thread_limit(threads):
        np.testing.assert_array_equal(last_points(point_row, n_rows + 2), expected)
    assert last_points(np.empty(0, np.int64), 3).tolist() == [-1, -1, -1]
