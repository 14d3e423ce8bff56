"""Configuration of the 3D CNN baseline (DeepNet): frozen dataclasses, loaded from one TOML file.

Every value the semantic3D.net paper gives (Section 3.3) is the default (``preset =
"paper"``): voxel sizes, cube size, channels, hidden units, dropout, batch size, number of
batches, rotation period, Adadelta. What the paper does not give is ours: Adadelta's
learning rate and rho (torch's defaults), tile sizes, checkpoints, the class list, the
prediction settings and the seed (docs/baseline_cnn.md lists every difference). A file
changes only what it names. ``preset = "cpu-short"`` starts from these values with a
training schedule short enough for a CPU (and says so in every model it trains).

.. code-block:: toml

    preset = "paper"

    [cubes]
    voxel_sizes_m = [0.025, 0.05, 0.1, 0.2, 0.4]
    cube_voxels = 16
    centring = "point"

    [network]
    channels = [16, 32, 64]
    hidden_units = 2048
    dropout = 0.5

    [training]
    batch_size = 100
    n_batches = 74700
    rotate_every = 100
    checkpoint_every = 1000
    seed = 0

    [prediction]
    tile_size_m = 25.6
    batch_size = 256
    device_batch_size = 16384
    precision = "auto"
    compile = "auto"
"""

from __future__ import annotations

import math
import numbers
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import semantic3d.core.config as config_file
from semantic3d.core.classes import LABEL_VALUES
from semantic3d.core.errors import ConfigError

__all__ = [
    "CENTRINGS",
    "COMPILE_CHOICES",
    "PRECISIONS",
    "PRESETS",
    "CnnConfig",
    "CubeConfig",
    "NetworkConfig",
    "PredictionConfig",
    "TrainingConfig",
    "config_from_dict",
    "config_to_dict",
    "load_config",
]


CENTRINGS: tuple[str, ...] = ("point", "corner")
"""How a cube sits on its point: ``"point"`` exactly centred (the paper);
``"corner"`` the block of the scan's grid around the grid corner nearest the point."""


PRECISIONS: tuple[str, ...] = ("auto", "float32")
"""Arithmetic of the network when labelling: ``"auto"`` float16 on a CUDA GPU (float32 on a
CPU, where bfloat16 is slower and changes labels), ``"float32"`` everywhere."""

COMPILE_CHOICES: tuple[str, ...] = ("auto", "always", "never")
"""``torch.compile`` of the network when labelling: ``"auto"`` once the points to label
make up for the compilation (see :mod:`~semantic3d.baselines.cnn.inference`)."""


@dataclass(frozen=True, slots=True)
class CubeConfig:
    """The network's input: one occupancy cube per scale, centred on the point.

    Attributes:
        voxel_sizes_m: voxel edge of each scale (the paper: 2.5, 5, 10, 20, 40 cm).
        cube_voxels: voxels along a cube's edge (the paper: 16).
        centring: ``"point"`` (the paper: each cube centred exactly on its point) or
            ``"corner"`` (centred on the nearest corner of the scan's grid, within half a
            voxel; models saved without this field were trained so).
    """

    voxel_sizes_m: tuple[float, ...] = (0.025, 0.05, 0.1, 0.2, 0.4)
    cube_voxels: int = 16
    centring: str = "point"

    def __post_init__(self) -> None:
        if not self.voxel_sizes_m:
            raise ConfigError("voxel_sizes_m: expected at least one voxel size")
        bad = [v for v in self.voxel_sizes_m if not (math.isfinite(v) and v > 0)]
        if bad:
            raise ConfigError(f"voxel_sizes_m: expected sizes > 0, found {bad}")
        if not _is_integer(self.cube_voxels) or self.cube_voxels < 8 or self.cube_voxels % 8:
            raise ConfigError(
                f"cube_voxels: expected a multiple of 8 (three 2x pools), found {self.cube_voxels!r}"
            )
        if self.centring not in CENTRINGS:
            raise ConfigError(
                f"centring: expected one of {list(CENTRINGS)}, found {self.centring!r}"
            )

    @property
    def n_scales(self) -> int:
        """Number of cubes per point."""
        return len(self.voxel_sizes_m)

    @property
    def reach_m(self) -> float:
        """How far from a point (in x or y) a point can change its cubes: the halo a tile
        needs for tiled cubes to equal whole-scan ones.

        Corner-centred cubes see cells up to half a cube plus half a voxel away. A
        point-centred cube reaches exactly half a cube (``C/2 * v``) from its point, up
        to float64 rounding of the fractions (~1e-10 m); the same half-voxel margin is
        kept for it, so both centrings use ``(C/2 + 1/2) * v`` (3.4 m for the paper's).
        """
        return (self.cube_voxels / 2 + 0.5) * max(self.voxel_sizes_m)


@dataclass(frozen=True, slots=True)
class NetworkConfig:
    """The network: per scale ``c(1,16) r m c(16,32) r m c(32,64) r m``, then
    ``f(n_scales*64*2^3, 2048) r d(0.5) f(2048, 8)``.

    Attributes:
        channels: output channels of the three 3x3x3 convolutions of each scale's path.
        hidden_units: width of the fully connected layer.
        dropout: dropout probability after it.
    """

    channels: tuple[int, ...] = (16, 32, 64)
    hidden_units: int = 2048
    dropout: float = 0.5

    def __post_init__(self) -> None:
        if len(self.channels) != 3:
            raise ConfigError(
                f"channels: expected 3 values (one per convolution), found {list(self.channels)}"
            )
        for index, value in enumerate(self.channels):
            _check_positive(f"channels[{index}]", value)
        _check_positive("hidden_units", self.hidden_units)
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"dropout: expected a probability in [0, 1), found {self.dropout}")


@dataclass(frozen=True, slots=True)
class TrainingConfig:
    """The paper's schedule: Adadelta, class-balanced batches of 100, 74,700 batches, a
    random rotation of the scan about z every 100 batches. Adadelta's settings, the class
    list, the tiles, checkpoints and the seed are not in the paper.

    Attributes:
        batch_size: points per mini-batch.
        n_batches: mini-batches of the whole run.
        rotate_every: batches between two random rotations of the training scans about z
            (the cubes of those batches are generated together, from one rotation).
        learning_rate: Adadelta's learning rate (torch's default 1.0; the paper names
            Adadelta without its settings).
        rho: Adadelta's decay (torch's default 0.9).
        checkpoint_every: batches between two checkpoints (0: none).
        classes: label values to train on; empty: every class present in the labels.
        tile_size_m: tile edge of the training scans' tile stores.
        seed: seed of sampling, rotations, initial weights and dropout.
        autocast: train under bfloat16 autocast on a CUDA GPU that has it (ignored on a
            CPU, where training is float32).
    """

    batch_size: int = 100
    n_batches: int = 74_700
    rotate_every: int = 100
    learning_rate: float = 1.0
    rho: float = 0.9
    checkpoint_every: int = 1000
    classes: tuple[int, ...] = ()
    tile_size_m: float = 25.6
    seed: int = 0
    autocast: bool = True

    def __post_init__(self) -> None:
        _check_positive("batch_size", self.batch_size)
        _check_positive("n_batches", self.n_batches)
        _check_positive("rotate_every", self.rotate_every)
        if not self.learning_rate > 0:
            raise ConfigError(f"learning_rate: expected > 0, found {self.learning_rate}")
        if not 0.0 < self.rho < 1.0:
            raise ConfigError(f"rho: expected a value in (0, 1), found {self.rho}")
        if not _is_integer(self.checkpoint_every) or self.checkpoint_every < 0:
            raise ConfigError(
                f"checkpoint_every: expected an integer >= 0, found {self.checkpoint_every!r}"
            )
        bad = [c for c in self.classes if c not in LABEL_VALUES]
        if bad:
            raise ConfigError(f"classes: expected label values in {LABEL_VALUES}, found {bad}")
        if not self.tile_size_m > 0:
            raise ConfigError(f"tile_size_m: expected > 0, found {self.tile_size_m}")
        if not _is_integer(self.seed) or self.seed < 0:
            raise ConfigError(f"seed: expected a non-negative integer, found {self.seed!r}")


@dataclass(frozen=True, slots=True)
class PredictionConfig:
    """Streaming prediction of whole scans, tile by tile.

    Attributes:
        tile_size_m: tile edge; each tile is read with a halo of the cubes' reach.
        batch_size: points per network call on a CPU.
        device_batch_size: points per network call on a GPU (thousands fill the card).
        chunk_size: points per chunk read from the scan.
        deduplicate: classify each distinct set of cubes once (points whose cubes are
            identical get the same label; the labels are those of per-point prediction).
        precision: ``"auto"`` (float16 on a GPU, float32 on a CPU) or ``"float32"``.
        compile: ``torch.compile`` the network: ``"auto"`` (once the points to label pay
            for it), ``"always"`` or ``"never"``; a failed compilation runs eagerly.
    """

    tile_size_m: float = 25.6
    batch_size: int = 256
    device_batch_size: int = 16384
    chunk_size: int = 1 << 20
    deduplicate: bool = True
    precision: str = "auto"
    compile: str = "auto"

    def __post_init__(self) -> None:
        if not self.tile_size_m > 0:
            raise ConfigError(f"tile_size_m: expected > 0, found {self.tile_size_m}")
        _check_positive("batch_size", self.batch_size)
        _check_positive("device_batch_size", self.device_batch_size)
        _check_positive("chunk_size", self.chunk_size)
        if self.precision not in PRECISIONS:
            raise ConfigError(
                f"precision: expected one of {list(PRECISIONS)}, found {self.precision!r}"
            )
        if self.compile not in COMPILE_CHOICES:
            raise ConfigError(
                f"compile: expected one of {list(COMPILE_CHOICES)}, found {self.compile!r}"
            )


@dataclass(frozen=True, slots=True)
class CnnConfig:
    """The whole baseline configuration (defaults: the paper's values where it gives them)."""

    preset: str = "paper"
    cubes: CubeConfig = field(default_factory=CubeConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    prediction: PredictionConfig = field(default_factory=PredictionConfig)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ConfigError(f"preset: expected one of {sorted(PRESETS)}, found {self.preset!r}")


PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "paper": {},
    "cpu-short": {"training": {"n_batches": 1500, "checkpoint_every": 500}},
}
"""Starting values of each preset (over the defaults); a file's own values win."""


def config_from_dict(data: dict[str, Any], *, source: str = "config") -> CnnConfig:
    """Build a configuration from nested dicts (TOML / JSON shape); unknown keys rejected.

    The preset's values are laid under the file's: ``preset = "cpu-short"`` with
    ``[training] n_batches = 300`` trains 300 batches.
    """
    preset = data.get("preset", "paper")
    merged: dict[str, Any] = dict(data)
    if isinstance(preset, str) and preset in PRESETS:
        for table, values in PRESETS[preset].items():
            given = data.get(table, {})
            if isinstance(given, dict):
                merged[table] = {**values, **given}
    return config_file.config_from_dict(merged, CnnConfig, source=source)


def load_config(path: str | Path) -> CnnConfig:
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


def config_to_dict(config: CnnConfig) -> dict[str, Any]:
    """The configuration as nested dicts (tuples as lists)."""
    return cast("dict[str, Any]", config_file.config_to_dict(config))


def _is_integer(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _check_positive(name: str, value: object) -> None:
    if not _is_integer(value) or value < 1:  # type: ignore[operator]
        raise ConfigError(f"{name}: expected a positive integer, found {value!r}")
