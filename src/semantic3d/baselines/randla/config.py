"""Configuration of the RandLA-Net baseline: frozen dataclasses, loaded from one TOML file.

Two presets: ``"paper"`` (Hu et al. 2020's Semantic3D settings: 6 cm grid, five layers of
16-64-128-256-512 channels sampled 4-4-4-4-2, sub-clouds of 65,536 points, batches of 4,
100 epochs of 500 steps, colour input) and ``"cpu"`` (the default: four narrower layers,
sub-clouds of at most 16,384 points, a schedule of minutes on two cores). A file starts
from its preset and changes only what it names.

.. code-block:: toml

    preset = "cpu"

    [inputs]
    intensity = false
    rgb = false

    [blocks]
    voxel_size_m = 0.06
    tile_size_m = 12.0
    halo_m = 4.0
    max_points = 16384

    [network]
    k_neighbours = 16
    feature_channels = 8
    channels = [16, 32, 64, 128]
    ratios = [4, 4, 4, 4]
    dropout = 0.5

    [training]
    batch_size = 4
    n_batches = 800
    learning_rate = 0.01
    lr_decay = 0.75
    decay_every = 100
    seed = 0

    [prediction]
    seed = 0
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import semantic3d.core.config as config_file
from semantic3d.core.classes import LABEL_VALUES
from semantic3d.core.errors import ConfigError

__all__ = [
    "CENTRES",
    "CLASS_WEIGHTS",
    "PRESETS",
    "BlockConfig",
    "InputConfig",
    "NetworkConfig",
    "PredictionConfig",
    "RandlaConfig",
    "TrainingConfig",
    "config_from_dict",
    "config_to_dict",
    "load_config",
]

CENTRES: tuple[str, ...] = ("balanced", "uniform")
"""How training sub-clouds are centred: on a point of a class drawn in turn (``balanced``)
or on a point drawn uniformly over every labelled point (``uniform``)."""

CLASS_WEIGHTS: tuple[str, ...] = ("inverse", "sqrt", "none")
"""Weights of the classes in the loss, from their share ``f`` of the training points:
``1 / (f + 0.02)`` (the paper's), ``1 / sqrt(f)``, or none."""


@dataclass(frozen=True, slots=True)
class InputConfig:
    """What each point brings besides its coordinates (local xyz are always an input).

    Attributes:
        intensity: the scanner's intensity, divided by ``intensity_scale``.
        rgb: the colour, divided by 255.
        intensity_scale: what intensities are divided by (Semantic3D's span -2048..2047).
    """

    intensity: bool = False
    rgb: bool = False
    intensity_scale: float = 2048.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.intensity_scale) and self.intensity_scale > 0):
            raise ConfigError(f"intensity_scale: expected > 0, found {self.intensity_scale}")

    @property
    def n_inputs(self) -> int:
        """Input channels of a point: xyz, then intensity, then r g b."""
        return 3 + int(self.intensity) + 3 * int(self.rgb)


@dataclass(frozen=True, slots=True)
class BlockConfig:
    """How a scan becomes the point sets the network sees.

    A scan is cut into square tiles of ``tile_size_m`` (whole voxels); every tile is read
    with a halo of ``halo_m``, reduced to one point per occupied voxel of ``voxel_size_m``
    and labelled in one network pass, the labels kept for the tile's own points only. A
    tile whose block (tile and halo) holds more than ``max_points`` voxels is split into
    quarters (each with its own halo) until it fits. Training sub-clouds are blocks of the
    same width (``tile_size_m + 2 halo_m``) centred on a training point.

    Attributes:
        voxel_size_m: edge of the voxel grid points are reduced to.
        tile_size_m: edge of a tile.
        halo_m: context read around a tile.
        max_points: voxels of one network pass.
    """

    voxel_size_m: float = 0.06
    tile_size_m: float = 12.0
    halo_m: float = 4.0
    max_points: int = 16384

    def __post_init__(self) -> None:
        for name in ("voxel_size_m", "tile_size_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name}: expected > 0, found {value}")
        if not (math.isfinite(self.halo_m) and self.halo_m >= 0):
            raise ConfigError(f"halo_m: expected >= 0, found {self.halo_m}")
        if self.tile_size_m < 2 * self.voxel_size_m:
            raise ConfigError(
                f"tile_size_m: expected at least two voxels ({2 * self.voxel_size_m} m), "
                f"found {self.tile_size_m}"
            )
        _check_positive("max_points", self.max_points)
        if self.max_points < 16:
            raise ConfigError(f"max_points: expected at least 16, found {self.max_points}")

    @property
    def cells_per_tile(self) -> int:
        """Voxels along a tile's edge (the tile is ``tile_size_m`` rounded up to voxels)."""
        return max(2, math.ceil(self.tile_size_m / self.voxel_size_m - 1e-9))

    @property
    def window_m(self) -> float:
        """Half-width of a training sub-cloud: half a tile and its halo."""
        return self.cells_per_tile * self.voxel_size_m / 2 + self.halo_m


@dataclass(frozen=True, slots=True)
class NetworkConfig:
    """RandLA-Net: an encoder of dilated residual blocks (local spatial encoding and
    attentive pooling over ``k_neighbours``), each followed by random sampling by its
    ratio, a decoder of nearest-neighbour upsampling with skip links, per-point logits.

    Attributes:
        k_neighbours: neighbours of every point at every level.
        feature_channels: width of the first per-point layer.
        channels: ``d_out`` of each encoder layer (its block outputs ``2 d_out``).
        ratios: random sampling ratio after each encoder layer.
        dropout: dropout before the last layer.
    """

    k_neighbours: int = 16
    feature_channels: int = 8
    channels: tuple[int, ...] = (16, 32, 64, 128)
    ratios: tuple[int, ...] = (4, 4, 4, 4)
    dropout: float = 0.5

    def __post_init__(self) -> None:
        _check_positive("k_neighbours", self.k_neighbours)
        _check_positive("feature_channels", self.feature_channels)
        if not self.channels:
            raise ConfigError("channels: expected at least one layer")
        for index, value in enumerate(self.channels):
            _check_positive(f"channels[{index}]", value)
            if value % 2:
                raise ConfigError(f"channels[{index}]: expected an even number, found {value}")
        if len(self.ratios) != len(self.channels):
            raise ConfigError(
                f"ratios: expected one per layer ({len(self.channels)}), found {list(self.ratios)}"
            )
        for index, value in enumerate(self.ratios):
            _check_positive(f"ratios[{index}]", value)
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"dropout: expected a probability in [0, 1), found {self.dropout}")

    @property
    def n_layers(self) -> int:
        """Encoder layers."""
        return len(self.channels)


@dataclass(frozen=True, slots=True)
class TrainingConfig:
    """Adam on class-weighted cross-entropy, sub-clouds drawn in rounds.

    Attributes:
        batch_size: sub-clouds per step (at least 2).
        n_batches: steps of the run.
        round_batches: steps whose sub-clouds are drawn together (one read of each tile).
        learning_rate: Adam's initial step.
        lr_decay: the step is multiplied by this every ``decay_every`` batches (the
            ``cpu`` preset's 0.75 takes the step to a tenth over its 800 batches; a longer
            run should raise ``decay_every`` in proportion).
        decay_every: batches between two decays (the paper: an epoch of 500 steps).
        centres: ``balanced`` or ``uniform`` (see :data:`CENTRES`).
        class_weights: ``inverse``, ``sqrt`` or ``none`` (see :data:`CLASS_WEIGHTS`).
        rotate: rotate each sub-cloud about z by a random angle.
        flip: mirror each sub-cloud in x with probability one half.
        scale_min: smallest random scale of each axis.
        scale_max: largest random scale of each axis.
        jitter_m: standard deviation of the noise added to coordinates.
        checkpoint_every: batches between two checkpoints (0: none).
        classes: label values to train on; empty: every class present in the labels.
        tile_size_m: tile edge of the training scans' tile stores.
        seed: seed of sampling, augmentation, initial weights and dropout.
    """

    batch_size: int = 4
    n_batches: int = 800
    round_batches: int = 25
    learning_rate: float = 0.01
    lr_decay: float = 0.75  # 0.01 -> 0.001 over 800 batches: chosen by grouped CV
    decay_every: int = 100
    centres: str = "balanced"
    class_weights: str = "sqrt"
    rotate: bool = True
    flip: bool = True
    scale_min: float = 0.9
    scale_max: float = 1.1
    jitter_m: float = 0.001
    checkpoint_every: int = 100
    classes: tuple[int, ...] = ()
    tile_size_m: float = 12.0
    seed: int = 0

    def __post_init__(self) -> None:
        _check_positive("batch_size", self.batch_size)
        if self.batch_size < 2:
            raise ConfigError(
                f"batch_size: expected at least 2 sub-clouds (batch normalisation needs more "
                f"than one point at the coarsest level), found {self.batch_size}"
            )
        _check_positive("n_batches", self.n_batches)
        _check_positive("round_batches", self.round_batches)
        _check_positive("decay_every", self.decay_every)
        if not (math.isfinite(self.learning_rate) and self.learning_rate > 0):
            raise ConfigError(f"learning_rate: expected > 0, found {self.learning_rate}")
        if not 0.0 < self.lr_decay <= 1.0:
            raise ConfigError(f"lr_decay: expected a value in (0, 1], found {self.lr_decay}")
        if self.centres not in CENTRES:
            raise ConfigError(f"centres: expected one of {list(CENTRES)}, found {self.centres!r}")
        if self.class_weights not in CLASS_WEIGHTS:
            raise ConfigError(
                f"class_weights: expected one of {list(CLASS_WEIGHTS)}, found "
                f"{self.class_weights!r}"
            )
        if not 0.0 < self.scale_min <= self.scale_max:
            raise ConfigError(
                f"scale_min, scale_max: expected 0 < min <= max, found {self.scale_min}, "
                f"{self.scale_max}"
            )
        if not (math.isfinite(self.jitter_m) and self.jitter_m >= 0):
            raise ConfigError(f"jitter_m: expected >= 0, found {self.jitter_m}")
        if not _is_integer(self.checkpoint_every) or self.checkpoint_every < 0:
            raise ConfigError(
                f"checkpoint_every: expected an integer >= 0, found {self.checkpoint_every!r}"
            )
        bad = [c for c in self.classes if c not in LABEL_VALUES]
        if bad:
            raise ConfigError(f"classes: expected label values in {LABEL_VALUES}, found {bad}")
        if not (math.isfinite(self.tile_size_m) and self.tile_size_m > 0):
            raise ConfigError(f"tile_size_m: expected > 0, found {self.tile_size_m}")
        if not _is_integer(self.seed) or self.seed < 0:
            raise ConfigError(f"seed: expected a non-negative integer, found {self.seed!r}")


@dataclass(frozen=True, slots=True)
class PredictionConfig:
    """Labelling whole scans, tile by tile.

    Attributes:
        chunk_size: points per chunk read from the scan.
        seed: seed of the random sampling inside the network (the labels are a function
            of the scan, the model and this seed).
        parallel_tiles: tiles labelled at a time (0: one per CPU thread, see
            ``baselines.common.device.cpu_threads``): on the CPU each on one thread; on a
            GPU their host work side by side, their network passes one at a time.
        half: on a GPU, run the network under bfloat16 autocast.
        compile: on a GPU, compile the network with ``torch.compile``.
        votes: network passes per block whose class probabilities are averaged; pass
            ``v`` draws its own random order and turns the block by ``v / votes`` of a
            turn about z (1: one pass, its classes; the time grows with the votes).
    """

    chunk_size: int = 1 << 20
    seed: int = 0
    parallel_tiles: int = 0
    half: bool = True
    compile: bool = False
    votes: int = 1

    def __post_init__(self) -> None:
        _check_positive("chunk_size", self.chunk_size)
        if not _is_integer(self.votes) or not 1 <= self.votes <= 64:
            raise ConfigError(f"votes: expected an integer from 1 to 64, found {self.votes!r}")
        if not _is_integer(self.parallel_tiles) or self.parallel_tiles < 0:
            raise ConfigError(
                f"parallel_tiles: expected an integer >= 0, found {self.parallel_tiles!r}"
            )
        if not _is_integer(self.seed) or self.seed < 0:
            raise ConfigError(f"seed: expected a non-negative integer, found {self.seed!r}")


@dataclass(frozen=True, slots=True)
class RandlaConfig:
    """The whole baseline configuration (defaults: the ``cpu`` preset)."""

    preset: str = "cpu"
    inputs: InputConfig = field(default_factory=InputConfig)
    blocks: BlockConfig = field(default_factory=BlockConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    prediction: PredictionConfig = field(default_factory=PredictionConfig)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ConfigError(f"preset: expected one of {sorted(PRESETS)}, found {self.preset!r}")


PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "cpu": {},
    "paper": {
        "inputs": {"rgb": True},
        "blocks": {"voxel_size_m": 0.06, "tile_size_m": 20.0, "halo_m": 6.0, "max_points": 65536},
        "network": {"channels": [16, 64, 128, 256, 512], "ratios": [4, 4, 4, 4, 2]},
        "training": {
            "batch_size": 4,
            "n_batches": 50_000,
            "round_batches": 100,
            "learning_rate": 0.01,
            "lr_decay": 0.95,
            "decay_every": 500,
            "centres": "uniform",
            "class_weights": "inverse",
            "scale_min": 0.8,
            "scale_max": 1.2,
            "checkpoint_every": 1000,
            "tile_size_m": 20.0,
        },
    },
}
"""Starting values of each preset (over the dataclass defaults, which are ``cpu``'s); a
file's own values win."""


def preset_config(name: str) -> RandlaConfig:
    """The configuration of preset ``name``."""
    return config_from_dict({"preset": name}, source=f"preset {name!r}")


def config_from_dict(data: dict[str, Any], *, source: str = "config") -> RandlaConfig:
    """Build a configuration from nested dicts (TOML / JSON shape); unknown keys rejected.

    The preset's values are laid under the file's.
    """
    preset = data.get("preset", "cpu")
    merged: dict[str, Any] = dict(data)
    if isinstance(preset, str) and preset in PRESETS:
        for table, values in PRESETS[preset].items():
            given = data.get(table, {})
            if isinstance(given, dict):
                merged[table] = {**values, **given}
    return config_file.config_from_dict(merged, RandlaConfig, source=source)


def load_config(path: str | Path) -> RandlaConfig:
    """Read a TOML configuration; raises :class:`ConfigError` naming the file and key."""
    import tomllib

    path = Path(path)
    try:
        with path.open("rb") as stream:
            data = tomllib.load(stream)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the configuration: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    return config_from_dict(data, source=str(path))


def config_to_dict(config: RandlaConfig) -> dict[str, Any]:
    """The configuration as nested dicts (tuples as lists)."""
    return cast("dict[str, Any]", config_file.config_to_dict(config))


def _is_integer(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _check_positive(name: str, value: object) -> None:
    if not _is_integer(value) or value < 1:  # type: ignore[operator]
        raise ConfigError(f"{name}: expected a positive integer, found {value!r}")
