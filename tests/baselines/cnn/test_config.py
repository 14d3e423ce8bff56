"""Configuration: the paper's values by default, presets, bad values named."""

from __future__ import annotations

from pathlib import Path

import pytest

from semantic3d.baselines.cnn.config import CnnConfig, config_from_dict, load_config
from semantic3d.core.errors import ConfigError


def test_defaults_are_the_papers_values() -> None:
    config = CnnConfig()
    assert config.preset == "paper"
    assert config.cubes.voxel_sizes_m == (0.025, 0.05, 0.1, 0.2, 0.4)
    assert config.cubes.cube_voxels == 16
    assert config.network.channels == (16, 32, 64) and config.network.hidden_units == 2048
    assert config.network.dropout == 0.5
    training = config.training
    assert (training.batch_size, training.n_batches, training.rotate_every) == (100, 74_700, 100)
    assert config.cubes.reach_m == pytest.approx(3.4)


def test_a_preset_sets_defaults_that_the_file_overrides(tmp_path: Path) -> None:
    path = tmp_path / "short.toml"
    path.write_text('preset = "cpu-short"\n[training]\ncheckpoint_every = 7\n')
    config = load_config(path)
    assert config.training.n_batches == 1500 and config.training.checkpoint_every == 7
    assert config.cubes == CnnConfig().cubes


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"preset": "fast"}, r"preset: expected one of \['cpu-short', 'paper'\], found 'fast'"),
        ({"cubes": {"cube_voxels": 12}}, r"\[cubes\] cube_voxels: expected a multiple of 8"),
        ({"cubes": {"voxel_sizes_m": [0.1, -1.0]}}, r"voxel_sizes_m: expected sizes > 0"),
        ({"network": {"channels": [16, 32]}}, r"channels: expected 3 values"),
        ({"network": {"dropout": 1.0}}, r"dropout: expected a probability in \[0, 1\)"),
        ({"training": {"batch_size": 0}}, r"batch_size: expected a positive integer, found 0"),
        ({"training": {"classes": [9]}}, r"classes: expected label values"),
        ({"prediction": {"tile": 3}}, r"\[prediction\]: unknown key\(s\) \['tile'\]"),
    ],
)
def test_bad_values_are_named(data: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        config_from_dict(data, source="cnn.toml")
