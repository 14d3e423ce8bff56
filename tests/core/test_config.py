"""The configuration loader: strict types, unknown keys, "none", messages, TOML round trip."""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.config import (
    config_from_dict,
    config_to_dict,
    config_to_toml,
    read_config,
)
from semantic3d.core.errors import ConfigError, Semantic3DError


@dataclass(frozen=True, slots=True)
class Model:
    n_trees: int = 10
    depth: int | None = 4
    rate: float = 0.5
    verbose: bool = False
    name: str = "forest"
    choice: str | float | None = "auto"
    sizes: tuple[int, ...] = (1, 2)
    depths: tuple[int | None, ...] = (3, None)

    def __post_init__(self) -> None:
        if self.depth is not None and self.depth < 1:
            raise ConfigError(f'depth: expected a positive integer or "none", found {self.depth}')


@dataclass(frozen=True, slots=True)
class Inner:
    size_m: float = 1.0


@dataclass(frozen=True, slots=True)
class Outer:
    inner: Inner = field(default_factory=Inner)
    label: str = "x"


@dataclass(frozen=True, slots=True)
class Settings:
    model: Model = field(default_factory=Model)
    outer: Outer = field(default_factory=Outer)
    seed: int = 0


def _read(tmp_path: Path, text: str) -> Settings:
    path = tmp_path / "model.toml"
    path.write_text(text)
    return read_config(path, Settings)


def _rejects(tmp_path: Path, text: str, match: str) -> str:
    with pytest.raises(ConfigError, match=match) as info:
        _read(tmp_path, text)
    assert str(info.value).startswith(str(tmp_path / "model.toml") + ": ")
    return str(info.value)


def test_config_error_is_a_value_error_of_the_package() -> None:
    assert issubclass(ConfigError, Semantic3DError) and issubclass(ConfigError, ValueError)


def test_the_one_config_error_is_re_exported_and_extended() -> None:
    from semantic3d.datasets.simulator import SimulationConfigError
    from semantic3d.features import ConfigError as FeaturesConfigError

    assert FeaturesConfigError is ConfigError
    assert issubclass(SimulationConfigError, ConfigError)


def test_an_empty_file_gives_the_defaults(tmp_path: Path) -> None:
    assert _read(tmp_path, "") == Settings()


def test_values_are_read_in_nested_tables(tmp_path: Path) -> None:
    got = _read(
        tmp_path,
        "seed = 3\n[model]\nrate = 2\nsizes = [5]\ndepths = []\nchoice = 0.25\n[outer.inner]\nsize_m = 1e-3\n",
    )
    assert got.seed == 3 and got.outer.inner.size_m == 1e-3
    assert got.model.rate == 2.0 and isinstance(got.model.rate, float)
    assert got.model.sizes == (5,) and got.model.depths == () and got.model.choice == 0.25


def test_an_unknown_section_is_rejected(tmp_path: Path) -> None:
    _rejects(
        tmp_path,
        "[forest]\nx = 1\n",
        r"model\.toml: unknown section\(s\) \['forest'\]: expected some of \['model', 'outer', 'seed'\]",
    )


def test_unknown_keys_are_rejected_per_table(tmp_path: Path) -> None:
    message = _rejects(
        tmp_path,
        "[model]\ntrees = 1\ndepht = 2\n[outer.inner]\nsize = 3\n",
        r"\[model\]: unknown key\(s\) \['depht', 'trees'\]: expected some of \['choice', ",
    )
    assert r"[outer.inner]: unknown key(s) ['size']: expected some of ['size_m']" in message


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("[model]\nn_trees = 2.5\n", r"\[model\] n_trees: expected an integer, found 2\.5$"),
        ("[model]\nn_trees = true\n", r"\[model\] n_trees: expected an integer, found true$"),
        ('[model]\nn_trees = "3"\n', r'\[model\] n_trees: expected an integer, found "3"$'),
        ('[model]\nrate = "0.5"\n', r'\[model\] rate: expected a number, found "0\.5"$'),
        ("[model]\nverbose = 1\n", r"\[model\] verbose: expected true or false, found 1$"),
        ("[model]\nname = 3\n", r"\[model\] name: expected a string, found 3$"),
        ("[model]\nsizes = 3\n", r"\[model\] sizes: expected a list, found 3$"),
        ("[model]\nsizes = [1, 2.0]\n", r"\[model\] sizes\[1\]: expected an integer, found 2\.0$"),
        ("[model]\nchoice = [1]\n", r'choice: expected a string, a number or "none", found \[1\]$'),
        ("model = 3\n", r"model\.toml: \[model\]: expected a table, found 3$"),
        ("[model.n_trees]\n", r"\[model\] n_trees: expected an integer, found \{\}$"),
        ("seed = 1.5\n", r"model\.toml: seed: expected an integer, found 1\.5$"),
        ("[outer]\ninner = 1\n", r"\[outer\.inner\]: expected a table, found 1$"),
        ("[model]\nname = 1979-05-27\n", r"\[model\] name: expected a string, found 1979-05-27$"),
    ],
)
def test_a_wrong_type_is_rejected_with_file_key_expected_and_found(
    tmp_path: Path, text: str, match: str
) -> None:
    _rejects(tmp_path, text, match)


def test_an_out_of_range_value_is_reported_with_its_table(tmp_path: Path) -> None:
    _rejects(
        tmp_path,
        "[model]\ndepth = -3\n",
        r'^\S*model\.toml: \[model\] depth: expected a positive integer or "none", found -3$',
    )


def test_every_problem_is_reported_at_once_one_line_each(tmp_path: Path) -> None:
    message = _rejects(
        tmp_path, "seed = 1.5\nextra = 1\n[model]\nrate = true\nverbose = 0\n", "seed"
    )
    lines = message.splitlines()
    assert len(lines) == 4
    assert all(line.startswith(str(tmp_path / "model.toml") + ": ") for line in lines)
    assert any("[model] verbose: expected true or false" in line for line in lines)


@pytest.mark.parametrize("spelling", ["none", "None", "NONE"])
def test_none_is_spelled_none_where_a_field_admits_none(tmp_path: Path, spelling: str) -> None:
    got = _read(
        tmp_path,
        f'[model]\ndepth = "{spelling}"\nchoice = "{spelling}"\ndepths = [1, "{spelling}"]\n',
    )
    assert got.model.depth is None and got.model.choice is None
    assert got.model.depths == (1, None)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('[model]\nn_trees = "none"\n', r'\[model\] n_trees: expected an integer, found "none"$'),
        ('[model]\nname = "none"\n', None),  # a plain string where None is not admitted
        ('[model]\nsizes = ["none"]\n', r'sizes\[0\]: expected an integer, found "none"$'),
        ('seed = "none"\n', r'seed: expected an integer, found "none"$'),
    ],
)
def test_none_is_not_taken_where_a_field_does_not_admit_it(
    tmp_path: Path, text: str, match: str | None
) -> None:
    if match is None:
        assert _read(tmp_path, text).model.name == "none"
    else:
        _rejects(tmp_path, text, match)


def test_none_is_written_as_none_and_tuples_as_lists() -> None:
    plain = config_to_dict(Settings(model=Model(depth=None, depths=(None, 2))))
    assert plain["model"]["depth"] == "none" and plain["model"]["depths"] == ["none", 2]
    assert plain["outer"] == {"inner": {"size_m": 1.0}, "label": "x"}


def test_an_unreadable_or_invalid_file_is_reported(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"absent\.toml: cannot read the configuration"):
        read_config(tmp_path / "absent.toml", Settings)
    _rejects(tmp_path, "[model\n", r"model\.toml: not valid TOML")


def test_the_source_names_a_dict(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"^request: \[model\] n_trees: expected an integer"):
        config_from_dict({"model": {"n_trees": "x"}}, Settings, source="request")


def test_only_dataclasses_are_configurations() -> None:
    with pytest.raises(TypeError, match="expected a dataclass"):
        config_from_dict({}, dict)
    with pytest.raises(TypeError, match="expected a dataclass instance"):
        config_to_dict(Settings)


_text = st.text(st.characters(exclude_categories=("Cs",)), max_size=12)
_finite = st.floats(allow_nan=False, width=64)
_models = st.builds(
    Model,
    n_trees=st.integers(-(2**63), 2**63 - 1),
    depth=st.none() | st.integers(1, 10**6),
    rate=_finite,
    verbose=st.booleans(),
    name=_text,
    choice=st.none() | _text.filter(lambda s: s.lower() != "none") | _finite,
    sizes=st.lists(st.integers(-5, 5), max_size=4).map(tuple),
    depths=st.lists(st.none() | st.integers(0, 9), max_size=4).map(tuple),
)
_settings = st.builds(
    Settings,
    model=_models,
    outer=st.builds(Outer, inner=st.builds(Inner, size_m=_finite), label=_text),
    seed=st.integers(0, 2**32),
)


@settings(max_examples=150, deadline=None)
@given(config=_settings)
def test_a_configuration_survives_the_toml_round_trip(config: Settings) -> None:
    text = config_to_toml(config)
    assert config_from_dict(tomllib.loads(text), Settings) == config
    assert config_from_dict(config_to_dict(config), Settings) == config


def test_toml_text_has_tables_after_the_top_level_keys() -> None:
    text = config_to_toml(dataclasses.replace(Settings(), seed=7))
    assert text.startswith("seed = 7\n\n[model]\n")
    assert '\n[outer]\nlabel = "x"\n\n[outer.inner]\nsize_m = 1.0\n' in text
