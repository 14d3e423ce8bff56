"""Configuration of the covariance baseline: frozen dataclasses, loaded from one TOML file.

Every section and key is optional; unknown sections or keys are rejected with the file,
section and key named. TOML has no null: ``max_depth = "none"`` grows trees fully.

.. code-block:: toml

    [features]
    base_voxel_size_m = 0.025
    n_levels = 9
    k_neighbours = 10

    [forest]
    n_estimators = 50
    max_depth = 20

    [sampling]
    points_per_class = 10000
    seed = 0

    [prediction]
    tile_size_m = 25.6

    [grid_search]
    n_estimators = [25, 50]
    max_depth = [10, 20, "none"]
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from semantic3d.core.classes import LABEL_VALUES
from semantic3d.features.config import ConfigError, FeatureConfig
from semantic3d.features.tiling import DEFAULT_TILE_SIZE_M

_NONE = "none"


@dataclass(frozen=True, slots=True)
class ForestConfig:
    """Random-forest hyper-parameters (see ``CovarianceClassifier``).

    Defaults: best mean IoU over all points of held-out Oakland scans (0.581 at depth 20
    vs 0.569 at 15 and 0.547 at 10, docs/baseline_covariance.md). The grid search scores
    the class-balanced sample instead and prefers depth 10 there.
    """

    n_estimators: int = 50
    max_depth: int | None = 20
    min_samples_leaf: int = 1
    max_features: str | float | int = "sqrt"

    def __post_init__(self) -> None:
        _check_positive("forest.n_estimators", self.n_estimators)
        if self.max_depth is not None:
            _check_positive("forest.max_depth", self.max_depth)
        _check_positive("forest.min_samples_leaf", self.min_samples_leaf)


@dataclass(frozen=True, slots=True)
class SamplingConfig:
    """Class-balanced sampling of training points.

    Attributes:
        points_per_class: points drawn per class over all training scans (all of a
            class's points when it has fewer).
        classes: label values to train on; empty means every class present in the
            training labels. A listed class without any labelled point is an error.
        seed: seed of the sampling and of the forest.
    """

    points_per_class: int = 10_000
    classes: tuple[int, ...] = ()
    seed: int = 0

    def __post_init__(self) -> None:
        _check_positive("sampling.points_per_class", self.points_per_class)
        bad = [c for c in self.classes if c not in LABEL_VALUES]
        if bad:
            raise ConfigError(
                f"sampling.classes: expected label values in {LABEL_VALUES}, found {bad}"
            )


@dataclass(frozen=True, slots=True)
class PredictionConfig:
    """Bounded-memory prediction.

    Attributes:
        tile_size_m: tile edge for scans processed tile by tile.
        max_points_in_memory: scans up to this many points are processed whole in memory
            (identical results, less overhead); larger ones tile by tile.
        chunk_size: points per chunk read from the scan.
    """

    tile_size_m: float = DEFAULT_TILE_SIZE_M
    max_points_in_memory: int = 4_000_000
    chunk_size: int = 1 << 20

    def __post_init__(self) -> None:
        if not self.tile_size_m > 0:
            raise ConfigError(f"prediction.tile_size_m: expected > 0, found {self.tile_size_m}")
        _check_positive("prediction.chunk_size", self.chunk_size)
        if self.max_points_in_memory < 0:
            raise ConfigError(
                f"prediction.max_points_in_memory: expected >= 0, found {self.max_points_in_memory}"
            )


@dataclass(frozen=True, slots=True)
class GridSearchConfig:
    """Grid of forest hyper-parameters searched with cross-validation grouped by scan."""

    n_estimators: tuple[int, ...] = (25, 50, 100)
    max_depth: tuple[int | None, ...] = (6, 10, 20, None)
    min_samples_leaf: tuple[int, ...] = (1,)
    max_features: tuple[str | float | int, ...] = ("sqrt",)
    n_splits: int = 5
    scoring: str = "jaccard_macro"

    def __post_init__(self) -> None:
        if self.n_splits < 2:
            raise ConfigError(f"grid_search.n_splits: expected >= 2, found {self.n_splits}")
        for name in ("n_estimators", "max_depth", "min_samples_leaf", "max_features"):
            if not getattr(self, name):
                raise ConfigError(f"grid_search.{name}: expected at least one value")

    @property
    def param_grid(self) -> dict[str, list[Any]]:
        """The grid as ``GridSearchCV`` takes it."""
        return {
            "n_estimators": list(self.n_estimators),
            "max_depth": list(self.max_depth),
            "min_samples_leaf": list(self.min_samples_leaf),
            "max_features": list(self.max_features),
        }


@dataclass(frozen=True, slots=True)
class CovarianceConfig:
    """The whole baseline configuration."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    forest: ForestConfig = field(default_factory=ForestConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    prediction: PredictionConfig = field(default_factory=PredictionConfig)
    grid_search: GridSearchConfig = field(default_factory=GridSearchConfig)


_SECTIONS: dict[str, type[Any]] = {
    "features": FeatureConfig,
    "forest": ForestConfig,
    "sampling": SamplingConfig,
    "prediction": PredictionConfig,
    "grid_search": GridSearchConfig,
}


def load_config(path: str | Path) -> CovarianceConfig:
    """Read a TOML configuration; raises :class:`ConfigError` naming the file and key."""
    path = Path(path)
    try:
        with path.open("rb") as stream:
            data = tomllib.load(stream)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the configuration: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    return config_from_dict(data, source=str(path))


def config_from_dict(data: dict[str, Any], *, source: str = "config") -> CovarianceConfig:
    """Build a configuration from nested dicts (TOML / JSON shape); unknown keys rejected."""
    unknown = sorted(set(data) - set(_SECTIONS))
    if unknown:
        raise ConfigError(
            f"{source}: unknown section(s) {unknown}: expected some of {sorted(_SECTIONS)}"
        )
    sections: dict[str, Any] = {}
    for name, cls in _SECTIONS.items():
        values = data.get(name, {})
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: [{name}]: expected a table, found {values!r}")
        sections[name] = _build_section(cls, values, where=f"{source}: [{name}]")
    return CovarianceConfig(**sections)


def config_to_dict(config: CovarianceConfig) -> dict[str, dict[str, Any]]:
    """The configuration as nested dicts (``None`` written as ``"none"``, tuples as lists)."""
    return {
        name: {
            f.name: _to_plain(getattr(getattr(config, name), f.name))
            for f in dataclasses.fields(cls)
        }
        for name, cls in _SECTIONS.items()
    }


def _build_section(cls: type[Any], values: dict[str, Any], *, where: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}: expected some of {sorted(fields)}")
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        default = getattr(cls(), key)
        kwargs[key] = _coerce(value, default, where=f"{where} {key}")
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _coerce(value: Any, default: Any, *, where: str) -> Any:
    """Check ``value`` against the type of ``default`` (tuples element-wise)."""
    if isinstance(default, tuple):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where}: expected a list, found {value!r}")
        return tuple(_scalar(v, where=where) for v in value)
    scalar = _scalar(value, where=where)
    if isinstance(default, bool):
        if not isinstance(scalar, bool):
            raise ConfigError(f"{where}: expected true or false, found {value!r}")
    elif isinstance(default, float):
        if isinstance(scalar, bool) or not isinstance(scalar, int | float):
            raise ConfigError(f"{where}: expected a number, found {value!r}")
        return float(scalar)
    elif isinstance(default, int) and (isinstance(scalar, bool) or not isinstance(scalar, int)):
        if scalar is None and where.endswith("max_depth"):
            return None
        raise ConfigError(f"{where}: expected an integer, found {value!r}")
    return scalar


def _scalar(value: Any, *, where: str) -> Any:
    if isinstance(value, str) and value.lower() == _NONE:
        return None
    if isinstance(value, dict | list):
        raise ConfigError(f"{where}: expected a single value, found {value!r}")
    return value


def _to_plain(value: Any) -> Any:
    if value is None:
        return _NONE
    if isinstance(value, tuple):
        return [_to_plain(v) for v in value]
    return value


def _check_positive(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{name}: expected a positive integer, found {value!r}")
