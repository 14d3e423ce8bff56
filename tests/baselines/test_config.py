"""The TOML configuration: defaults, round trip, unknown keys and bad values rejected."""

from __future__ import annotations

from pathlib import Path

import pytest

from semantic3d.baselines.covariance.config import (
    CovarianceConfig,
    config_from_dict,
    config_to_dict,
    load_config,
)
from semantic3d.features import ConfigError


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
        ("[sampling]\nclasses = [9]\n", r"sampling.classes: expected label values"),
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
