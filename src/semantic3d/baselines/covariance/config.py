"""Configuration of the covariance baseline: frozen dataclasses, loaded from one TOML file.

Read by :mod:`semantic3d.core.config`: every section and key is optional, unknown sections
or keys are rejected with the file, section and key named, types are checked strictly.
TOML has no null: ``max_depth = "none"`` grows trees fully. A top-level ``preset`` picks
the values of every key the file leaves out: ``"default"`` (the dataclass defaults) or
``"paper"`` (the method as the semantic3D.net paper describes it: :func:`preset_config`).

.. code-block:: toml

    preset = "default"

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

    [context]
    potts_weight = 4.0  # the context step (0 turns it off)
    max_graph_nodes = 65536  # a denser tile's graph is cut in squares (0: whole tiles)

    [grid_search]
    n_estimators = [25, 50]
    max_depth = [10, 20, "none"]
"""

from __future__ import annotations

import numbers
import tomllib
from dataclasses import dataclass, field
from dataclasses import fields as dataclass_fields
from pathlib import Path
from typing import Any, cast

import semantic3d.core.config as config_file
from semantic3d.core.classes import LABEL_VALUES
from semantic3d.core.errors import ConfigError
from semantic3d.features.config import FeatureConfig
from semantic3d.features.names import CYLINDER_FEATURES
from semantic3d.features.tiling import DEFAULT_TILE_SIZE_M

__all__ = [
    "ConfigError",
    "ContextConfig",
    "CovarianceConfig",
    "ForestConfig",
    "GridSearchConfig",
    "PredictionConfig",
    "SamplingConfig",
    "config_from_dict",
    "config_to_dict",
    "load_config",
    "preset_config",
]

DEFAULT_POTTS_WEIGHT = 4.0
"""Default weight of the context step (the cross-validation's inner splits choose 1 to 8,
median 4; docs/baseline_covariance.md). The ``paper`` preset has no context step."""

PRESETS = ("default", "paper")
"""Names a configuration's ``preset`` may take."""

_MAX_FEATURES_NAMES = ("sqrt", "log2")

MaxFeatures = str | float | int | None
"""``max_features`` of the forest: ``"sqrt"``, ``"log2"``, a fraction in (0, 1], a count,
or None (``"none"`` in a file) for all features."""


@dataclass(frozen=True, slots=True)
class ForestConfig:
    """Random-forest hyper-parameters (see ``CovarianceClassifier``).

    Defaults: best mean IoU over all points of 4 held-out Oakland scans (depth 20 vs 15
    and 10, docs/baseline_covariance.md). The grid search scores the class-balanced
    sample instead and prefers depth 10 there; ``train --grid-search`` fits its choice.
    """

    n_estimators: int = 50
    max_depth: int | None = 20
    min_samples_leaf: int = 1
    max_features: MaxFeatures = "sqrt"

    def __post_init__(self) -> None:
        _check_positive("n_estimators", self.n_estimators)
        _check_max_depth("max_depth", self.max_depth)
        _check_positive("min_samples_leaf", self.min_samples_leaf)
        _check_max_features("max_features", self.max_features)


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
        _check_positive("points_per_class", self.points_per_class)
        bad = [c for c in self.classes if c not in LABEL_VALUES]
        if bad:
            raise ConfigError(f"classes: expected label values in {LABEL_VALUES}, found {bad}")
        if not _is_integer(self.seed) or self.seed < 0:
            raise ConfigError(f"seed: expected a non-negative integer, found {self.seed!r}")


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
            raise ConfigError(f"tile_size_m: expected > 0, found {self.tile_size_m}")
        _check_positive("chunk_size", self.chunk_size)
        if not _is_integer(self.max_points_in_memory) or self.max_points_in_memory < 0:
            raise ConfigError(
                f"max_points_in_memory: expected >= 0, found {self.max_points_in_memory!r}"
            )


@dataclass(frozen=True, slots=True)
class ContextConfig:
    """Spatial context on the classifier's class probabilities.

    The level-0 voxels of a scan (or of a tile) are joined to their ``n_neighbours``
    nearest (by the centroid of their points) and labelled by minimising a Potts energy,
    ``sum -log p(label) + potts_weight * (neighbours labelled differently)``, with
    alpha-expansion (:mod:`~semantic3d.baselines.covariance.context`). Chosen by the
    leave-scans-out cross-validation (docs/baseline_covariance.md): +0.06 mIoU on Oakland,
    the weight chosen per fold on inner splits (1 to 8, median 4). On by default; a model
    saved before the step existed predicts without it.

    Attributes:
        potts_weight: cost of two neighbouring voxels taking different labels, in units
            of -log probability; 0 turns the step off (labels are the most probable class).
        n_neighbours: graph edges per voxel.
        max_sweeps: alpha-expansion passes over the classes (each pass lowers the energy;
            one pass gives nearly all of the gain).
        max_graph_nodes: a tile's graph of more voxels is cut in quadtree squares of at
            most this many (down to squares of a 64th of the tile's edge), which are
            labelled apart and at the same time: the densest tile, near the scanner,
            holds over half a scan's voxels, and its cut alone would otherwise end every
            many-thread run on one thread. 0 cuts whole tiles (a model saved before the
            setting existed does). The labels do not depend on the thread count either way.
    """

    potts_weight: float = DEFAULT_POTTS_WEIGHT
    n_neighbours: int = 8
    max_sweeps: int = 1
    max_graph_nodes: int = 1 << 16

    def __post_init__(self) -> None:
        if isinstance(self.potts_weight, bool) or not (
            isinstance(self.potts_weight, numbers.Real) and self.potts_weight >= 0
        ):
            raise ConfigError(f"potts_weight: expected a number >= 0, found {self.potts_weight!r}")
        _check_positive("n_neighbours", self.n_neighbours)
        _check_positive("max_sweeps", self.max_sweeps)
        if not _is_integer(self.max_graph_nodes) or self.max_graph_nodes < 0:
            raise ConfigError(
                f"max_graph_nodes: expected an integer >= 0, found {self.max_graph_nodes!r}"
            )

    def __setstate__(self, state: list[Any]) -> None:
        """Unpickled: a model saved before ``max_graph_nodes`` existed cut whole tiles, and
        still does (its labels as when it was saved)."""
        values = list(state)
        values += [0] * (len(_CONTEXT_FIELDS) - len(values))
        for name, value in zip(_CONTEXT_FIELDS, values, strict=True):
            object.__setattr__(self, name, value)

    @property
    def enabled(self) -> bool:
        """Whether prediction runs the context step."""
        return self.potts_weight > 0


_CONTEXT_FIELDS = tuple(f.name for f in dataclass_fields(ContextConfig))


@dataclass(frozen=True, slots=True)
class GridSearchConfig:
    """Grid of forest hyper-parameters searched with cross-validation grouped by scan.

    Attributes:
        select_forest: ``train`` runs the grid search first and fits the best parameters
            (the paper's five-fold cross-validation, grouped by scan here;
            ``train --grid-search`` sets it);
            they replace ``[forest]``'s and are recorded in the model file.
        n_splits: folds, grouped by scan (fewer when there are fewer training scans).
        scoring: scikit-learn scorer of the held-out folds' sample.
    """

    select_forest: bool = False
    n_estimators: tuple[int, ...] = (25, 50, 100)
    max_depth: tuple[int | None, ...] = (6, 10, 20, None)
    min_samples_leaf: tuple[int, ...] = (1,)
    max_features: tuple[MaxFeatures, ...] = ("sqrt",)
    n_splits: int = 5
    scoring: str = "jaccard_macro"

    def __post_init__(self) -> None:
        if not _is_integer(self.n_splits) or self.n_splits < 2:
            raise ConfigError(f"n_splits: expected >= 2, found {self.n_splits!r}")
        for name in ("n_estimators", "max_depth", "min_samples_leaf", "max_features"):
            if not getattr(self, name):
                raise ConfigError(f"{name}: expected at least one value")
        for index, value in enumerate(self.n_estimators):
            _check_positive(f"n_estimators[{index}]", value)
        for index, depth in enumerate(self.max_depth):
            _check_max_depth(f"max_depth[{index}]", depth)
        for index, value in enumerate(self.min_samples_leaf):
            _check_positive(f"min_samples_leaf[{index}]", value)
        for index, choice in enumerate(self.max_features):
            _check_max_features(f"max_features[{index}]", choice)

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
    """The whole baseline configuration.

    Attributes:
        preset: the preset the values not given in a file came from (``"default"`` or
            ``"paper"``, see :func:`preset_config`); informative once built.
    """

    preset: str = "default"
    features: FeatureConfig = field(default_factory=FeatureConfig)
    forest: ForestConfig = field(default_factory=ForestConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    prediction: PredictionConfig = field(default_factory=PredictionConfig)
    grid_search: GridSearchConfig = field(default_factory=GridSearchConfig)
    context: ContextConfig = field(default_factory=ContextConfig)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ConfigError(
                f"preset: expected one of {', '.join(PRESETS)}, found {self.preset!r}"
            )


def preset_config(name: str) -> CovarianceConfig:
    """The configuration of a preset.

    - ``"default"``: the dataclass defaults, the configuration that cross-validated best
      on scans left out of training (docs/baseline_covariance.md);
    - ``"paper"``: the method as Section 3.2 of the semantic3D.net paper describes it
      (details from our reading of Hackel et al. 2016): covariance and moment features of
      the k nearest neighbours, height features of vertical cylinders only, the forest
      chosen by a five-fold grid search (grouped by scan: ours), no context step.
    """
    if name == "default":
        return CovarianceConfig()
    if name == "paper":
        return CovarianceConfig(
            preset="paper",
            features=FeatureConfig(
                cylinders=True, spherical_height=False, cylinder_features=CYLINDER_FEATURES
            ),
            grid_search=GridSearchConfig(select_forest=True),
            context=ContextConfig(potts_weight=0.0),
        )
    raise ConfigError(f"preset: expected one of {', '.join(PRESETS)}, found {name!r}")


def load_config(path: str | Path) -> CovarianceConfig:
    """Read a TOML configuration; raises :class:`ConfigError` naming the file and key."""
    path = Path(path)
    try:
        with path.open("rb") as stream:
            preset = tomllib.load(stream).get("preset")
    except (OSError, tomllib.TOMLDecodeError):
        preset = None  # read_config reports it
    if not isinstance(preset, str) or preset == "default":
        return config_file.read_config(path, CovarianceConfig)
    with path.open("rb") as stream:
        return config_from_dict(tomllib.load(stream), source=str(path))


def config_from_dict(data: dict[str, Any], *, source: str = "config") -> CovarianceConfig:
    """Build a configuration from nested dicts (TOML / JSON shape); unknown keys rejected.

    A ``preset`` key other than ``"default"`` takes every value not in ``data`` from
    :func:`preset_config`.
    """
    preset = data.get("preset")
    if isinstance(preset, str) and preset != "default":
        try:
            base = config_to_dict(preset_config(preset))
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}") from None
        data = _merged(base, data)
    return config_file.config_from_dict(data, CovarianceConfig, source=source)


def _merged(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``override`` on top of ``base``, table by table."""
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            merged[key] = _merged(base[key], value)
        else:
            merged[key] = value
    return merged


def config_to_dict(config: CovarianceConfig) -> dict[str, dict[str, Any]]:
    """The configuration as nested dicts (``None`` written as ``"none"``, tuples as lists)."""
    return cast("dict[str, dict[str, Any]]", config_file.config_to_dict(config))


def _is_integer(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _check_positive(name: str, value: object) -> None:
    if not _is_integer(value) or value < 1:  # type: ignore[operator]
        raise ConfigError(f"{name}: expected a positive integer, found {value!r}")


def _check_max_depth(name: str, value: object) -> None:
    if value is not None and (not _is_integer(value) or value < 1):  # type: ignore[operator]
        raise ConfigError(f'{name}: expected a positive integer or "none", found {value!r}')


def _check_max_features(name: str, value: object) -> None:
    if value is None or value in _MAX_FEATURES_NAMES:
        return
    if _is_integer(value) and value >= 1:  # type: ignore[operator]
        return
    if isinstance(value, float) and 0.0 < value <= 1.0:
        return
    raise ConfigError(
        f'{name}: expected "sqrt", "log2", "none", a fraction in (0, 1] or a positive '
        f"integer, found {value!r}"
    )
