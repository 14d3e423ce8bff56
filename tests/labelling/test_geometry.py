"""Server-side geometry: polygon splits through a known camera and RANSAC model fits."""

from __future__ import annotations

import numpy as np
import pytest

from semantic3d.core.errors import ShapeError
from semantic3d.labelling.geometry import (
    CylinderModel,
    LineModel,
    PlaneModel,
    SphereModel,
    fit_model,
    points_in_polygon,
    project_to_ndc,
    select_in_polygon,
)


def _look_at_perspective(eye, target, fov_deg=60.0, aspect=1.5, near=0.1, far=100.0):
    """Row-major view-projection of an OpenGL camera (z up world), built by hand."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, -forward
    view[:3, 3] = -view[:3, :3] @ eye
    f = 1 / np.tan(np.radians(fov_deg) / 2)
    projection = np.zeros((4, 4))
    projection[0, 0], projection[1, 1] = f / aspect, f
    projection[2, 2], projection[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    projection[3, 2] = -1
    return projection @ view


def test_top_orthographic_split_is_a_vertical_prism() -> None:
    # Top view of x, y in [-10, 10] (NDC = x / 10, y / 10): the polygon cuts through every z.
    matrix = np.diag([0.1, 0.1, -0.01, 1.0])
    xyz = np.array([[1.0, 1.0, -50.0], [1.0, 1.0, 50.0], [6.0, 1.0, 0.0], [2.0, -1.0, 3.0]])
    triangle = [(-0.2, -0.2), (0.5, -0.2), (0.5, 0.5)]  # x in [-2, 5], y <= x
    assert select_in_polygon(xyz, matrix, triangle).tolist() == [True, True, False, True]


def test_perspective_split_with_a_known_camera() -> None:
    matrix = _look_at_perspective(eye=(0, -10, 0), target=(0, 0, 0))
    ahead = np.array([[0.0, 0.0, 0.0], [0.0, 5.0, 0.0], [3.0, 0.0, 0.0], [0.0, -20.0, 0.0]])
    ndc, in_front = project_to_ndc(ahead, matrix)
    np.testing.assert_allclose(ndc[:2], 0.0, atol=1e-12)  # on the optical axis
    f = 1 / np.tan(np.radians(30))
    np.testing.assert_allclose(ndc[2], [3.0 / 10 * f / 1.5, 0.0])
    assert in_front.tolist() == [True, True, True, False]  # the last one is behind the camera
    small_square = [(-0.1, -0.1), (0.1, -0.1), (0.1, 0.1), (-0.1, 0.1)]
    # Behind the camera projects (with w < 0) near the centre too: it must stay outside.
    assert select_in_polygon(ahead, matrix, small_square).tolist() == [True, True, False, False]


def test_polygon_even_odd_rule_on_a_concave_polygon() -> None:
    u_shape = [(0, 0), (3, 0), (3, 3), (2, 3), (2, 1), (1, 1), (1, 3), (0, 3)]
    points = np.array([[0.5, 2.0], [1.5, 2.0], [2.5, 2.0], [1.5, 0.5], [4.0, 1.0]])
    assert points_in_polygon(points, u_shape).tolist() == [True, False, True, True, False]


@pytest.mark.parametrize(
    ("matrix", "polygon", "match"),
    [
        (np.eye(3), [(0, 0), (1, 0), (0, 1)], "4×4 matrix"),
        (np.eye(4), [(0, 0), (1, 0)], "at least 3"),
        (np.eye(4), [(0, 0), (1, np.nan), (0, 1)], "finite vertex"),
    ],
)
def test_bad_camera_or_polygon_is_refused(matrix, polygon, match) -> None:
    with pytest.raises(ShapeError, match=match):
        select_in_polygon(np.zeros((2, 3)), matrix, polygon)


def _with_outliers(points: np.ndarray, rng, n: int, low, high) -> np.ndarray:
    return np.vstack([points, rng.uniform(low, high, (n, 3))])


def test_ransac_plane_on_noisy_points_with_outliers() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-10, 10, (3000, 2))
    z = 0.2 * xy[:, 0] - 0.1 * xy[:, 1] + 5 + rng.normal(0, 0.01, 3000)
    points = _with_outliers(np.column_stack([xy, z]), rng, 1500, (-10, -10, 0), (10, 10, 10))
    fit = fit_model("plane", points, tolerance_m=0.04)
    assert isinstance(fit.model, PlaneModel)
    expected = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    assert abs(abs(fit.model.normal @ expected) - 1) < 1e-4
    assert fit.inliers[:3000].mean() > 0.99 and fit.inliers[3000:].mean() < 0.05
    assert fit.rms_m < 0.015


def test_ransac_cylinder_recovers_axis_and_radius() -> None:
    rng = np.random.default_rng(2)
    axis = np.array([0.1, 0.2, 1.0]) / np.linalg.norm([0.1, 0.2, 1.0])
    u = np.cross(axis, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    t, angle = rng.uniform(0, 6, 3000), rng.uniform(0, 2 * np.pi, 3000)
    centre = np.array([100.0, 50.0, 2.0])
    surface = (
        centre
        + t[:, None] * axis
        + 0.3 * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * v)
        + rng.normal(0, 0.004, (3000, 3))
    )
    points = _with_outliers(surface, rng, 600, centre - 1.5, centre + 1.5)
    fit = fit_model("cylinder", points, tolerance_m=0.015)
    assert isinstance(fit.model, CylinderModel)
    assert abs(fit.model.radius_m - 0.3) < 0.005
    assert abs(abs(fit.model.axis @ axis) - 1) < 1e-3
    assert fit.inliers[:3000].mean() > 0.98


def test_ransac_sphere_and_line() -> None:
    rng = np.random.default_rng(3)
    direction = rng.normal(size=(2000, 3))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    sphere = np.array([3.0, 4.0, 5.0]) + 1.5 * direction + rng.normal(0, 0.005, (2000, 3))
    fit = fit_model("sphere", _with_outliers(sphere, rng, 800, 0, 8), tolerance_m=0.02)
    assert isinstance(fit.model, SphereModel)
    np.testing.assert_allclose(fit.model.centre, [3, 4, 5], atol=0.005)
    assert abs(fit.model.radius_m - 1.5) < 0.005

    t = rng.uniform(-5, 5, 500)
    wire = np.array([1.0, 2.0, 3.0]) + t[:, None] * np.array([0.6, 0.0, 0.8])
    wire += rng.normal(0, 0.003, wire.shape)
    fit = fit_model("line", _with_outliers(wire, rng, 200, -5, 5), tolerance_m=0.01)
    assert isinstance(fit.model, LineModel)
    assert abs(abs(fit.model.direction @ [0.6, 0.0, 0.8]) - 1) < 1e-4


def test_seeds_choose_between_two_planes() -> None:
    rng = np.random.default_rng(4)
    big = np.column_stack([rng.uniform(-10, 10, (4000, 2)), rng.normal(0, 0.005, 4000)])
    wall = np.column_stack(
        [rng.uniform(-3, 3, 1000), np.full(1000, 2.0), rng.uniform(0.5, 4, 1000)]
    )
    points = np.vstack([big, wall])
    fit = fit_model("plane", points, tolerance_m=0.02, seeds=[(0, 2, 1), (1, 2, 3), (-1, 2, 2)])
    assert abs(abs(fit.model.normal[1]) - 1) < 1e-3  # the wall, not the bigger ground


@pytest.mark.parametrize(
    ("points", "tolerance", "match"),
    [(np.zeros((2, 3)), 0.1, "at least 3 points"), (np.zeros((5, 3)), 0.0, "positive distance")],
)
def test_bad_fit_input_is_refused(points, tolerance, match) -> None:
    with pytest.raises(ShapeError, match=match):
        fit_model("plane", points, tolerance_m=tolerance)
