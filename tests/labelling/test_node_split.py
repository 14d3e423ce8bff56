"""A split over the octree nodes marks exactly the points the pass over every point marks."""

from __future__ import annotations

import numpy as np
import pytest

from semantic3d.labelling import _op_kernels
from semantic3d.labelling.delta import empty_bits
from semantic3d.labelling.node_split import split_flips_by_nodes
from semantic3d.labelling.opening import open_label_session

from .conftest import NODE_CAPACITY


@pytest.fixture
def session(simulated_scan, tmp_path):
    opened = open_label_session(
        simulated_scan.cache.path,
        labels_path=tmp_path / "nodes.labels",
        node_capacity=NODE_CAPACITY,
    )
    yield opened
    opened.close()


def _views(xyz: np.ndarray) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Views and polygons: edges through points' exact coordinates, a camera inside the scan."""
    top = np.diag([0.02, 0.02, -0.001, 1.0])
    # Vertices on the projections of scan points: those points sit exactly on the edges.
    on_points = 0.02 * xyz[[10, 2000, 30000], :2]
    left, right = (int(np.argmin(np.abs(xyz[:, 0] - x))) for x in (-20.0, 20.0))
    u_left, u_right = 0.02 * xyz[left, 0], 0.02 * xyz[right, 0]
    square = np.array([[u_left, -0.6], [u_right, -0.6], [u_right, 0.6], [u_left, 0.6]])
    near, far, focal = 0.5, 300.0, 1.2
    a, b = -(far + near) / (far - near), -2 * far * near / (far - near)
    projection = np.array([[focal, 0, 0, 0], [0, focal, 0, 0], [0, 0, a, b], [0, 0, -1, 0]])
    eye = xyz.mean(axis=0) + np.array([0.0, 0.0, 2.0])  # inside the scan: nodes behind it
    view = np.array([[1, 0, 0, -eye[0]], [0, 0, 1, -eye[2]], [0, -1, 0, eye[1]], [0, 0, 0, 1]])
    star = np.array([[0.0, 0.9], [0.2, 0.2], [0.9, 0.1], [0.25, -0.15], [0.4, -0.8], [0.0, -0.3]])
    star = np.vstack([star, star[::-1][1:-1] * [-1, 1]])
    return [
        ("top, edges through points", top, on_points),
        ("top, square on points' x", top, square),
        ("perspective from inside", projection @ view, star),
    ]


def _every_point(session, xyz, editable, matrix, polygon, keep_inside) -> np.ndarray:
    """The split's bits from the pass over every point (the reference)."""
    expected = empty_bits(session.n_points)
    _op_kernels.split_flips(
        xyz, 0, session.origin, session.labels, session.working, editable,
        matrix, polygon, keep_inside, expected,
    )  # fmt: skip
    return expected


def test_a_split_over_nodes_equals_the_pass_over_every_point(session, simulated_scan) -> None:
    xyz = np.asarray(session.scan.xyz)
    local = xyz - session.origin
    rng = np.random.default_rng(4)
    session.labels[:] = simulated_scan.truth
    session.working[:] = rng.random(session.n_points) < 0.8
    editable = np.ones(9, bool)
    editable[3] = False  # a locked or hidden layer
    seen = {"retested": 0, "across": 0, "whole": 0, "inside": 0, "outside": 0}
    for name, matrix, polygon in _views(local):
        for keep_inside in (True, False):
            expected = _every_point(session, xyz, editable, matrix, polygon, keep_inside)
            flip = empty_bits(session.n_points)
            counts = split_flips_by_nodes(
                session, matrix, polygon, keep_inside=keep_inside, editable=editable, flip=flip
            )
            np.testing.assert_array_equal(flip, expected, err_msg=f"{name}, {keep_inside=}")
            assert 0 < _op_kernels.count_bits(flip) < session.n_points, name
            seen["retested"] += counts.points_retested
            seen["across"] += counts.nodes_across
            seen["whole"] += counts.nodes_whole
            seen["inside" if keep_inside else "outside"] += counts.nodes_skipped
    assert all(seen.values()), seen  # every path was taken, nodes inside and outside skipped


def test_a_split_over_nodes_on_threads_equals_it_on_one(session, simulated_scan, monkeypatch):
    """Tasks of a few nodes on 1 and 3 threads (each with its own mask, OR-ed in the end)
    mark the same bits, equal to the pass over every point, with the same counts."""
    monkeypatch.setattr("semantic3d.labelling.node_split.TASK_POINTS", 2000)
    xyz = np.asarray(session.scan.xyz)
    session.labels[:] = simulated_scan.truth
    session.working[:] = np.random.default_rng(5).random(session.n_points) < 0.7
    editable = np.ones(9, bool)
    editable[2] = False
    for name, matrix, polygon in _views(xyz - session.origin):
        for keep_inside in (True, False):
            expected = _every_point(session, xyz, editable, matrix, polygon, keep_inside)
            outcomes = []
            for threads in (1, 3):
                flip = empty_bits(session.n_points)
                counts = split_flips_by_nodes(
                    session, matrix, polygon, keep_inside=keep_inside, editable=editable,
                    flip=flip, threads=threads,
                )  # fmt: skip
                np.testing.assert_array_equal(flip, expected, err_msg=f"{name}, {threads=}")
                outcomes.append(counts)
            assert outcomes[0] == outcomes[1], name
            assert outcomes[0].points_whole + outcomes[0].points_across > 4 * 2000, name
