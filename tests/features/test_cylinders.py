"""Height features of vertical cylinders against a brute-force reference; their columns."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core import PointCloud
from semantic3d.core.errors import ShapeError
from semantic3d.features import ConfigError, FeatureConfig, compute_multiscale_features
from semantic3d.features.cylinders import compute_cylinder_features
from semantic3d.features.names import CYLINDER_FEATURES, GEOMETRIC_FEATURES


def reference(points: np.ndarray, queries: np.ndarray, radius_m: float) -> np.ndarray:
    """Every point tested against every query, float64 (squared distances, as the kernel:
    on the lattice many points lie at exactly the radius)."""
    rows = []
    for q in queries:
        dx, dy = points[:, 0] - q[0], points[:, 1] - q[1]
        inside = dx * dx + dy * dy <= radius_m * radius_m
        z = points[inside, 2]
        if z.size == 0:
            rows.append([0.0, 0.0, 0.0, 0.0])
        else:
            rows.append([z.max() - z.min(), q[2] - z.min(), z.max() - q[2], z.size])
    return np.array(rows)


@pytest.mark.parametrize("radius_m", [0.05, 0.3, 2.0])
def test_cylinders_match_a_brute_force_search(radius_m: float) -> None:
    rng = np.random.default_rng(3)
    # on a 1 cm lattice (as Oakland): many points at exactly the radius
    points = np.round(rng.uniform(-1.5, 1.5, size=(3000, 3)), 2)
    queries = np.vstack([points[:200], rng.uniform(-2.5, 2.5, size=(100, 3))])
    got = compute_cylinder_features(points, queries, radius_m=radius_m)
    np.testing.assert_allclose(got, reference(points, queries, radius_m), rtol=1e-6, atol=1e-6)
    assert (got[:200, 3] >= 1).all()  # a level point is in its own cylinder


def test_a_cylinder_ignores_height_but_not_horizontal_distance() -> None:
    points = np.array([[0.0, 0, 0], [0.0, 0, 30.0], [0.5, 0, 10], [2.0, 0, -5]])
    got = compute_cylinder_features(points, np.array([[0.0, 0, 1.0]]), radius_m=1.0)
    np.testing.assert_allclose(got, [[30.0, 1.0, 29.0, 3.0]])


def test_empty_cylinders_and_bad_inputs() -> None:
    far = compute_cylinder_features(np.zeros((2, 3)), np.array([[9.0, 9, 9]]), radius_m=1.0)
    assert np.array_equal(far, np.zeros((1, 4), np.float32))
    with pytest.raises(ShapeError, match="radius_m: expected a positive radius, found 0"):
        compute_cylinder_features(np.zeros((2, 3)), np.zeros((1, 3)), radius_m=0.0)
    with pytest.raises(ShapeError, match=r"expected \(n, 3\) and \(m, 3\), found \(2, 2\)"):
        compute_cylinder_features(np.zeros((2, 2)), np.zeros((1, 3)), radius_m=1.0)
    with pytest.raises(ConfigError, match="cylinder_radius_voxels: expected a radius in"):
        FeatureConfig(cylinder_radius_voxels=0.0)


def test_cylinder_columns_follow_the_knn_columns_at_every_level() -> None:
    config = FeatureConfig(
        base_voxel_size_m=0.1, n_levels=3, cylinders=True, cylinder_features=CYLINDER_FEATURES
    )
    per_level = GEOMETRIC_FEATURES + CYLINDER_FEATURES
    assert config.level_feature_names == per_level
    assert config.feature_names[len(per_level)] == "sum_of_eigenvalues@0.200m"
    without = FeatureConfig(spherical_height=False, cylinder_features=CYLINDER_FEATURES)
    assert "height_below" not in without.level_feature_names
    assert without.n_features == 9 * (len(GEOMETRIC_FEATURES) - 3 + len(CYLINDER_FEATURES))
    assert config.cylinder_radius_m(2) == pytest.approx(0.8)
    assert FeatureConfig().level_feature_names == (*GEOMETRIC_FEATURES, "cylinder_below")
    assert FeatureConfig(cylinders=False).level_feature_names == GEOMETRIC_FEATURES


def test_a_pole_stands_out_of_its_cylinder() -> None:
    """A 3 m pole on flat ground: the pole's top is 3 m above the ground around it."""
    grid = np.stack(np.meshgrid(np.arange(0, 4, 0.1), np.arange(0, 4, 0.1)), -1).reshape(-1, 2)
    ground = np.column_stack([grid, np.zeros(len(grid))])
    pole = np.column_stack([np.full(31, 2.02), np.full(31, 2.02), np.linspace(0, 3, 31)])
    cloud = PointCloud.from_arrays(np.vstack([ground, pole]) + 100.0)
    config = FeatureConfig(base_voxel_size_m=0.1, n_levels=3, cylinders=True)
    rows = compute_multiscale_features(cloud, config=config).point_values()
    below = rows[:, config.feature_names.index("cylinder_below@0.400m")]
    assert below[-1] == pytest.approx(3.0, abs=0.06)  # the pole's top
    assert np.abs(below[: len(ground)]).max() < 0.06  # the ground


def test_a_subset_of_cylinder_columns_is_the_same_values() -> None:
    rng = np.random.default_rng(5)
    cloud = PointCloud.from_arrays(rng.uniform(0, 4, size=(2000, 3)) + 50.0)
    every = FeatureConfig(base_voxel_size_m=0.2, n_levels=3, cylinder_features=CYLINDER_FEATURES)
    below = FeatureConfig(base_voxel_size_m=0.2, n_levels=3, cylinder_features=("cylinder_below",))
    assert below.level_feature_names == (*GEOMETRIC_FEATURES, "cylinder_below")
    full = compute_multiscale_features(cloud, config=every).point_values()
    part = compute_multiscale_features(cloud, config=below).point_values()
    for column, name in enumerate(below.feature_names):
        assert np.array_equal(part[:, column], full[:, every.feature_names.index(name)])
    with pytest.raises(ConfigError, match="cylinder_features: expected some of"):
        FeatureConfig(cylinder_features=("cylinder_above", "cylinder_range"))


def test_cylinders_do_not_depend_on_the_thread_count() -> None:
    from semantic3d.core.threads import thread_limit

    rng = np.random.default_rng(8)
    # dense near the origin, sparse far away (as a scan): blocks of queries cost unequal time
    radius = np.abs(rng.standard_cauchy(40_000)).clip(0.0, 200.0)
    angle = rng.uniform(0.0, 2.0 * np.pi, radius.size)
    points = np.column_stack(
        [radius * np.cos(angle), radius * np.sin(angle), rng.uniform(0, 3, radius.size)]
    )
    queries = points[::7]
    with thread_limit(1):
        one = compute_cylinder_features(points, queries, radius_m=0.5)
    with thread_limit(4):
        four = compute_cylinder_features(points, queries, radius_m=0.5)
    assert queries.shape[0] > 10 * 256  # many blocks of work
    np.testing.assert_array_equal(one, four)
    np.testing.assert_allclose(
        one[:300], reference(points, queries[:300], 0.5), rtol=1e-6, atol=1e-6
    )


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 3000),
    stack=st.integers(1, 80),
    radius_m=st.sampled_from([0.02, 0.05, 0.3, 1.7]),
    lattice=st.sampled_from([0.01, 0.025]),
    n_threads=st.sampled_from([1, 3]),
    seed=st.integers(0, 10_000),
)
def test_the_lowest_points_alone_give_cylinder_below_bit_for_bit(
    n: int, stack: int, radius_m: float, lattice: float, n_threads: int, seed: int
) -> None:
    """Walls: columns of ``stack`` points above one another on a lattice (many points at
    exactly the radius, equal heights, cells of more points than an insertion sort takes),
    and queries on the points, between them and far from them."""
    from semantic3d.core.threads import thread_limit

    rng = np.random.default_rng(seed)
    feet = np.round(rng.uniform(-0.6, 0.6, (max(1, n // stack), 2)) / lattice) * lattice
    heights = np.round(rng.uniform(-2.0, 8.0, (feet.shape[0], stack)) / lattice) * lattice
    points = np.column_stack([np.repeat(feet, stack, axis=0), heights.reshape(-1)]) + np.array(
        [5432.1, -876.5, 40.0]
    )
    queries = np.vstack(
        [points[:: max(1, points.shape[0] // 200)], rng.uniform(-3.0, 3.0, (60, 3)) + points[0]]
    )
    with thread_limit(n_threads):
        every = compute_cylinder_features(points, queries, radius_m=radius_m)
        below = compute_cylinder_features(
            points, queries, radius_m=radius_m, features=("cylinder_below",)
        )
    assert below.shape == (queries.shape[0], 1)
    assert np.array_equal(below[:, 0].view(np.uint32), every[:, 1].view(np.uint32))
    np.testing.assert_allclose(
        below[:, 0], reference(points, queries, radius_m)[:, 1], rtol=1e-6, atol=1e-4
    )


def test_any_subset_of_columns_into_any_destination() -> None:
    rng = np.random.default_rng(11)
    points = np.round(rng.uniform(-1.0, 1.0, (2000, 3)), 2)
    queries = points[::9]
    every = compute_cylinder_features(points, queries, radius_m=0.2)
    wide = np.zeros((queries.shape[0], 5), np.float32)
    for names in [("cylinder_range", "cylinder_points"), ("cylinder_below",), CYLINDER_FEATURES]:
        columns = [CYLINDER_FEATURES.index(name) for name in names]
        target = wide[:, 1 : 1 + len(names)]  # a column slice: not contiguous
        got = compute_cylinder_features(points, queries, radius_m=0.2, features=names, out=target)
        assert got is target
        assert np.array_equal(target, every[:, columns])
    with pytest.raises(ConfigError, match="features: expected some of"):
        compute_cylinder_features(
            points, queries, radius_m=0.2, features=("cylinder_above", "cylinder_range")
        )
    with pytest.raises(ShapeError, match=r"out: expected \(223, 1\), found \(223, 4\)"):
        compute_cylinder_features(
            points, queries, radius_m=0.2, features=("cylinder_below",), out=every
        )
    empty = compute_cylinder_features(
        np.zeros((0, 3)), queries, radius_m=0.2, features=("cylinder_below",)
    )
    assert np.array_equal(empty, np.zeros((queries.shape[0], 1), np.float32))
