"""The TOML configuration: defaults, round trip, unknown keys and bad values rejected."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.baselines.covariance.config import (
    CovarianceConfig,
    ForestConfig,
    GridSearchConfig,
    PredictionConfig,
    SamplingConfig,
    config_from_dict,
    config_to_dict,
    load_config,
    preset_config,
)
from semantic3d.core.classes import LABEL_VALUES
from semantic3d.core.config import config_to_toml
from semantic3d.features import ConfigError, FeatureConfig


def test_empty_file_gives_the_defaults(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("")
    assert load_config(path) == CovarianceConfig()


def test_values_are_read_and_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text(
        "[features]\nbase_voxel_size_m = 0.05\nn_levels = 8\nper_point = true\n"
        '[forest]\nmax_depth = "none"\nn_estimators = 30\n'
        "[sampling]\nclasses = [1, 2, 5]\npoints_per_class = 123\n"
        '[grid_search]\nmax_depth = [10, "none"]\n'
    )
    config = load_config(path)
    assert config.features.base_voxel_size_m == 0.05 and config.features.per_point
    assert config.forest.max_depth is None and config.forest.n_estimators == 30
    assert config.sampling.classes == (1, 2, 5)
    assert config.grid_search.max_depth == (10, None)
    assert config_from_dict(config_to_dict(config)) == config


def test_integers_are_accepted_for_sizes(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[prediction]\ntile_size_m = 50\n")
    assert load_config(path).prediction.tile_size_m == 50.0


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("[forest]\nn_trees = 3\n", r"\[forest\]: unknown key\(s\) \['n_trees'\]"),
        ("[model]\nx = 1\n", r"unknown section\(s\) \['model'\]"),
        ("[forest]\nn_estimators = 2.5\n", r"\[forest\] n_estimators: expected an integer"),
        ("[features]\nn_levels = 40\n", r"n_levels: expected 1..16, found 40"),
        ("[features]\nper_point = 1\n", r"per_point: expected true or false"),
        ("[sampling]\nclasses = [9]\n", r"\[sampling\] classes: expected label values"),
        (
            "[forest]\nmax_depth = -3\n",
            r'\[forest\] max_depth: expected a positive integer or "none", found -3',
        ),
        (
            '[forest]\nmax_depth = "deep"\n',
            r'\[forest\] max_depth: expected an integer or "none", found "deep"',
        ),
        (
            '[forest]\nn_estimators = "none"\n',
            r'\[forest\] n_estimators: expected an integer, found "none"',
        ),
        (
            '[forest]\nmax_features = "sqr"\n',
            r'\[forest\] max_features: expected "sqrt", "log2", "none"',
        ),
        ("[forest]\nmax_features = 1.5\n", r"max_features: expected .* a fraction in \(0, 1\]"),
        (
            "[grid_search]\nmax_depth = [10, 0]\n",
            r"\[grid_search\] max_depth\[1\]: expected a positive integer",
        ),
        (
            "[grid_search]\nmax_depth = [10, 2.5]\n",
            r"\[grid_search\] max_depth\[1\]: expected an integer or \"none\"",
        ),
        (
            "[grid_search]\nn_estimators = []\n",
            r"\[grid_search\] n_estimators: expected at least one value",
        ),
        ("[grid_search]\nn_splits = 1\n", r"\[grid_search\] n_splits: expected >= 2, found 1"),
        ("[prediction]\ntile_size_m = 0\n", r"\[prediction\] tile_size_m: expected > 0, found 0"),
        (
            "[prediction]\nchunk_size = 0\n",
            r"\[prediction\] chunk_size: expected a positive integer",
        ),
        (
            "[sampling]\nseed = -1\n",
            r"\[sampling\] seed: expected a non-negative integer, found -1",
        ),
        ("[sampling]\nclasses = 3\n", r"classes: expected a list"),
        ("forest = 3\n", r"\[forest\]: expected a table"),
        ("[forest\n", "not valid TOML"),
    ],
)
def test_bad_configuration_is_rejected_with_the_key_named(
    tmp_path: Path, text: str, match: str
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as info:
        load_config(path)
    assert "bad.toml" in str(info.value)


def test_missing_file_is_reported(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read the configuration"):
        load_config(tmp_path / "absent.toml")


def test_a_value_built_in_python_gets_the_same_checks() -> None:
    with pytest.raises(ConfigError, match=r'^max_depth: expected a positive integer or "none"'):
        ForestConfig(max_depth=0)
    with pytest.raises(ConfigError, match=r"^max_features\[1\]: expected \"sqrt\""):
        GridSearchConfig(max_features=("sqrt", "all"))


def test_the_model_file_form_is_unchanged() -> None:
    plain = config_to_dict(CovarianceConfig())
    assert plain["forest"] == {
        "n_estimators": 50,
        "max_depth": 20,
        "min_samples_leaf": 1,
        "max_features": "sqrt",
    }
    assert plain["grid_search"]["max_depth"] == [6, 10, 20, "none"]
    assert plain["sampling"]["classes"] == [] and plain["prediction"]["tile_size_m"] == 25.6


_positive = st.integers(1, 10**6)
_max_features = st.sampled_from(["sqrt", "log2", None]) | st.floats(0.01, 1.0) | _positive
_configs = st.builds(
    CovarianceConfig,
    features=st.builds(
        FeatureConfig,
        base_voxel_size_m=st.floats(1e-3, 10.0),
        n_levels=st.integers(1, 16),
        k_neighbours=st.integers(3, 256),
        per_point=st.booleans(),
        colour=st.booleans(),
        intensity=st.booleans(),
    ),
    forest=st.builds(
        ForestConfig,
        n_estimators=_positive,
        max_depth=st.none() | _positive,
        min_samples_leaf=_positive,
        max_features=_max_features,
    ),
    sampling=st.builds(
        SamplingConfig,
        points_per_class=_positive,
        classes=st.lists(st.sampled_from(LABEL_VALUES), unique=True).map(tuple),
        seed=st.integers(0, 2**32 - 1),
    ),
    prediction=st.builds(
        PredictionConfig,
        tile_size_m=st.floats(0.1, 1e4),
        max_points_in_memory=st.integers(0, 10**9),
        chunk_size=_positive,
    ),
    grid_search=st.builds(
        GridSearchConfig,
        n_estimators=st.lists(_positive, min_size=1, max_size=3).map(tuple),
        max_depth=st.lists(st.none() | _positive, min_size=1, max_size=3).map(tuple),
        min_samples_leaf=st.lists(_positive, min_size=1, max_size=3).map(tuple),
        max_features=st.lists(_max_features, min_size=1, max_size=3).map(tuple),
        n_splits=st.integers(2, 10),
        scoring=st.sampled_from(["jaccard_macro", "accuracy", "f1_macro"]),
    ),
)


@settings(max_examples=100, deadline=None)
@given(config=_configs)
def test_a_configuration_survives_the_toml_round_trip(
    tmp_path_factory: pytest.TempPathFactory, config: CovarianceConfig
) -> None:
    path = tmp_path_factory.mktemp("round") / "model.toml"
    path.write_text(config_to_toml(config))
    assert load_config(path) == config
    assert config_from_dict(tomllib.loads(path.read_text())) == config


def test_a_preset_fills_every_key_the_file_leaves_out(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('preset = "paper"\n[forest]\nn_estimators = 7\n')
    config = load_config(path)
    assert config == dataclasses.replace(
        preset_config("paper"), forest=ForestConfig(n_estimators=7)
    )
    assert config.features.cylinders and not config.features.spherical_height
    assert config.grid_search.select_forest
    assert config_from_dict(config_to_dict(config)) == config
    path.write_text('preset = "default"\n')
    assert load_config(path) == CovarianceConfig() == preset_config("default")


def test_an_unknown_preset_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('preset = "papr"\n')
    with pytest.raises(ConfigError, match=r"c.toml: preset: expected one of default, paper"):
        load_config(path)
