"""Configuration of the image baseline: frozen dataclasses, loaded from one TOML file.

``preset`` picks the defaults every other key overrides: ``"paper"`` takes the paper's
numbers (512 words per descriptor, 200 rectangles, superpixels at 3 settings) with
quick-shift in place of its mean-shift, and our face size and classifier settings,
``"small"`` is a quick setting for trials and tests (16 words, felzenszwalb superpixels,
small faces). Read by :mod:`semantic3d.core.config`: unknown keys are rejected and types
are checked strictly.

.. code-block:: toml

    preset = "paper"

    [cubemap]
    size = 256
    splat_radius_px = 1

    [words]
    n_words = 512
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import semantic3d.core.config as config_file
from semantic3d.core.errors import ConfigError

__all__ = [
    "PRESETS",
    "BoostingConfig",
    "CRFConfig",
    "FaceConfig",
    "ImageConfig",
    "RectangleConfig",
    "SuperpixelConfig",
    "UNetConfig",
    "WordsConfig",
    "config_from_dict",
    "config_to_dict",
    "load_config",
    "preset_config",
]

PRESETS = ("paper", "small")
SUPERPIXEL_METHODS = ("quickshift", "slic", "felzenszwalb")


def _positive(name: str, value: object) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{name}: expected a positive integer, found {value!r}")


@dataclass(frozen=True, slots=True)
class FaceConfig:
    """Cube faces the classifier works on.

    Attributes:
        size: face edge in pixels (classification resolution).
        splat_radius_px: splat radius of the render.
        chunk_size: points per chunk read.
    """

    size: int = 256
    splat_radius_px: int = 1
    chunk_size: int = 1 << 20

    def __post_init__(self) -> None:
        _positive("size", self.size)
        _positive("chunk_size", self.chunk_size)
        if not 0 <= self.splat_radius_px <= 16:
            raise ConfigError(f"splat_radius_px: expected 0..16, found {self.splat_radius_px}")


@dataclass(frozen=True, slots=True)
class WordsConfig:
    """Visual words: MiniBatchKMeans per continuous descriptor kind.

    Attributes:
        n_words: words per descriptor (the paper: 512).
        sample_pixels: pixels per kind the vocabulary is fitted on.
        daisy_step: grid step of the dense SIFT-like descriptors.
        daisy_radius: their radius in pixels.
        ltp_threshold: grey-level threshold of the ternary patterns (0..255).
    """

    n_words: int = 512
    sample_pixels: int = 200_000
    daisy_step: int = 4
    daisy_radius: int = 8
    ltp_threshold: float = 5.0

    def __post_init__(self) -> None:
        for name in ("n_words", "sample_pixels", "daisy_step", "daisy_radius"):
            _positive(name, getattr(self, name))
        if self.n_words < 2:
            raise ConfigError(f"n_words: expected >= 2, found {self.n_words}")
        if not self.ltp_threshold >= 0:
            raise ConfigError(f"ltp_threshold: expected >= 0, found {self.ltp_threshold}")


@dataclass(frozen=True, slots=True)
class RectangleConfig:
    """Rectangle bag-of-words features (TextonBoost shape filters).

    Attributes:
        n_rectangles: random rectangles around the pixel (the paper: 200); each counts
            one word of each descriptor kind, so features = n_rectangles × 5 kinds.
        max_offset_px: rectangle corners lie within this many pixels of the pixel.
        location: add the pixel's elevation angle and CIELab colour as features.
    """

    n_rectangles: int = 200
    max_offset_px: int = 40
    location: bool = True

    def __post_init__(self) -> None:
        _positive("n_rectangles", self.n_rectangles)
        _positive("max_offset_px", self.max_offset_px)


@dataclass(frozen=True, slots=True)
class BoostingConfig:
    """The boosted classifier (scikit-learn's HistGradientBoostingClassifier).

    Attributes:
        max_iter: boosting rounds.
        learning_rate: shrinkage.
        max_leaf_nodes: leaves per tree.
        pixels_per_class_per_face: training pixels drawn per class and face.
    """

    max_iter: int = 200
    learning_rate: float = 0.1
    max_leaf_nodes: int = 31
    pixels_per_class_per_face: int = 2000

    def __post_init__(self) -> None:
        _positive("max_iter", self.max_iter)
        _positive("max_leaf_nodes", self.max_leaf_nodes)
        _positive("pixels_per_class_per_face", self.pixels_per_class_per_face)
        if not 0 < self.learning_rate <= 1:
            raise ConfigError(f"learning_rate: expected in (0, 1], found {self.learning_rate}")


@dataclass(frozen=True, slots=True)
class SuperpixelConfig:
    """Superpixels at coarse-to-fine settings (scikit-image).

    Attributes:
        method: ``quickshift`` (mode seeking, of the family of the paper's mean-shift,
            which scikit-image lacks), ``slic`` or ``felzenszwalb``.
        scales: one setting per level: quickshift kernel size, SLIC segment count or
            felzenszwalb scale.
    """

    method: str = "quickshift"
    scales: tuple[float, ...] = (2.0, 3.0, 5.0)

    def __post_init__(self) -> None:
        if self.method not in SUPERPIXEL_METHODS:
            raise ConfigError(
                f"method: expected one of {SUPERPIXEL_METHODS}, found {self.method!r}"
            )
        if not self.scales or any(not s > 0 for s in self.scales):
            raise ConfigError(f"scales: expected positive settings, found {self.scales}")


@dataclass(frozen=True, slots=True)
class CRFConfig:
    """The CRF: pixel unaries, superpixel potentials, contrast-sensitive Potts smoothing.

    Attributes:
        pairwise_weight: weight of the Potts term between 4-neighbours.
        superpixel_weight: weight of the superpixel potentials (shared by the levels).
        n_cycles: alpha-expansion cycles over the classes.
    """

    pairwise_weight: float = 1.0
    superpixel_weight: float = 1.0
    n_cycles: int = 2

    def __post_init__(self) -> None:
        _positive("n_cycles", self.n_cycles)
        if self.pairwise_weight < 0 or self.superpixel_weight < 0:
            raise ConfigError("pairwise_weight, superpixel_weight: expected >= 0")


@dataclass(frozen=True, slots=True)
class UNetConfig:
    """The encoder-decoder variant (PyTorch).

    Attributes:
        base_channels: channels of the first level (doubled per level).
        depth: down-sampling levels.
        epochs: passes over the training faces.
        batch_size: crops per step.
        crop_px: training crop edge (faces are cropped at random).
        learning_rate: Adam's step size.
    """

    base_channels: int = 16
    depth: int = 3
    epochs: int = 30
    batch_size: int = 8
    crop_px: int = 128
    learning_rate: float = 2e-3

    def __post_init__(self) -> None:
        for name in ("base_channels", "depth", "epochs", "batch_size", "crop_px"):
            _positive(name, getattr(self, name))
        if self.crop_px % (1 << self.depth):
            raise ConfigError(
                f"crop_px: expected a multiple of 2**depth = {1 << self.depth}, found {self.crop_px}"
            )
        if not self.learning_rate > 0:
            raise ConfigError(f"learning_rate: expected > 0, found {self.learning_rate}")


@dataclass(frozen=True, slots=True)
class ImageConfig:
    """The whole image baseline configuration."""

    preset: str = "paper"
    seed: int = 0
    faces: FaceConfig = field(default_factory=FaceConfig)
    words: WordsConfig = field(default_factory=WordsConfig)
    rectangles: RectangleConfig = field(default_factory=RectangleConfig)
    boosting: BoostingConfig = field(default_factory=BoostingConfig)
    superpixels: SuperpixelConfig = field(default_factory=SuperpixelConfig)
    crf: CRFConfig = field(default_factory=CRFConfig)
    unet: UNetConfig = field(default_factory=UNetConfig)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ConfigError(f"preset: expected one of {PRESETS}, found {self.preset!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed: expected a non-negative integer, found {self.seed!r}")


_SMALL = {
    "preset": "small",
    "faces": {"size": 128},
    "words": {"n_words": 16, "sample_pixels": 20_000},
    "rectangles": {"n_rectangles": 30, "max_offset_px": 20},
    "boosting": {"max_iter": 40, "pixels_per_class_per_face": 300},
    "superpixels": {"method": "felzenszwalb", "scales": [30.0, 100.0, 300.0]},
    "crf": {"n_cycles": 1},
    "unet": {"base_channels": 8, "depth": 2, "epochs": 8, "batch_size": 4, "crop_px": 64},
}


def preset_config(name: str) -> ImageConfig:
    """The defaults of preset ``name`` (``paper`` or ``small``)."""
    if name == "paper":
        return ImageConfig()
    if name == "small":
        return config_file.config_from_dict(_SMALL, ImageConfig, source="preset small")
    raise ConfigError(f"preset: expected one of {PRESETS}, found {name!r}")


def _merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def config_from_dict(data: dict[str, Any], *, source: str = "config") -> ImageConfig:
    """A configuration from nested dicts: the preset's defaults, then ``data`` over them."""
    preset = data.get("preset", "paper")
    if preset not in PRESETS:
        raise ConfigError(f"{source}: preset: expected one of {PRESETS}, found {preset!r}")
    base = config_to_dict(preset_config(str(preset)))
    return config_file.config_from_dict(_merge(base, data), ImageConfig, source=source)


def load_config(path: str | Path) -> ImageConfig:
    """Read a TOML configuration (``preset`` first, then the file's keys)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the configuration: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    return config_from_dict(data, source=str(path))


def config_to_dict(config: ImageConfig) -> dict[str, Any]:
    """The configuration as nested dicts (TOML / JSON shape)."""
    return config_file.config_to_dict(config)


def with_seed(config: ImageConfig, seed: int | None) -> ImageConfig:
    """``config`` with another seed (None: unchanged)."""
    return config if seed is None else dataclasses.replace(config, seed=seed)
