"""RandLA-Net (Hu et al., CVPR 2020): random sampling, local spatial encoding, attentive
pooling and an encoder-decoder over voxel-reduced blocks, trained on sub-clouds of tiles
and applied to scans of any size tile by tile. See docs/baseline_randla.md.

Needs the ``[randla]`` extra (``pip install 'semantic3d[randla]'``: torch);
without it, importing any name that needs it raises
:class:`~semantic3d.core.errors.MissingExtraError`. Names are loaded on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.baselines.randla.config import (
        BlockConfig,
        InputConfig,
        NetworkConfig,
        PredictionConfig,
        RandlaConfig,
        TrainingConfig,
        config_from_dict,
        config_to_dict,
        load_config,
        preset_config,
    )
    from semantic3d.baselines.randla.crossval import cross_validate
    from semantic3d.baselines.randla.model import RandlaModel
    from semantic3d.baselines.randla.network import RandlaNet, build_network, count_parameters
    from semantic3d.baselines.randla.persistence import load_model, read_model_header, save_model
    from semantic3d.baselines.randla.training import train_randla_model

_EXPORTS = {
    "BlockConfig": "config",
    "InputConfig": "config",
    "NetworkConfig": "config",
    "PredictionConfig": "config",
    "RandlaConfig": "config",
    "TrainingConfig": "config",
    "config_from_dict": "config",
    "config_to_dict": "config",
    "load_config": "config",
    "preset_config": "config",
    "cross_validate": "crossval",
    "RandlaModel": "model",
    "RandlaNet": "network",
    "build_network": "network",
    "count_parameters": "network",
    "load_model": "persistence",
    "read_model_header": "persistence",
    "save_model": "persistence",
    "train_randla_model": "training",
}

__all__ = [
    "BlockConfig",
    "InputConfig",
    "NetworkConfig",
    "PredictionConfig",
    "RandlaConfig",
    "RandlaModel",
    "RandlaNet",
    "TrainingConfig",
    "build_network",
    "config_from_dict",
    "config_to_dict",
    "count_parameters",
    "cross_validate",
    "load_config",
    "load_model",
    "preset_config",
    "read_model_header",
    "save_model",
    "train_randla_model",
]

__getattr__, __dir__ = lazy_exports(
    __name__, {name: f"semantic3d.baselines.randla.{module}" for name, module in _EXPORTS.items()}
)
