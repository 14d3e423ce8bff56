"""The paper's 3D CNN baseline (DeepNet): multi-scale occupancy cubes per point and a
VGG-like 3D network, trained class-balanced and applied to whole scans tile by tile.
See docs/baseline_cnn.md.

Needs the ``[torch]`` extra (``pip install 'semantic3d[torch]'``); without it, importing
any name that needs torch raises :class:`~semantic3d.core.errors.MissingExtraError`.
Names are loaded on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.baselines.cnn.config import (
        CnnConfig,
        CubeConfig,
        NetworkConfig,
        PredictionConfig,
        TrainingConfig,
        config_from_dict,
        config_to_dict,
        load_config,
    )
    from semantic3d.baselines.cnn.crossval import (
        CrossValidationResult,
        FoldResult,
        cross_validate,
        scan_folds,
    )
    from semantic3d.baselines.cnn.cubes import (
        CentringError,
        Occupancy,
        build_occupancy,
        compute_corner_cells,
        compute_cubes,
        fill_cubes,
    )
    from semantic3d.baselines.cnn.model import CnnModel, DeviceError
    from semantic3d.baselines.cnn.network import DeepNet, build_network, count_parameters
    from semantic3d.baselines.cnn.persistence import (
        ModelFileError,
        load_model,
        read_model_header,
        save_model,
    )
    from semantic3d.baselines.cnn.training import (
        CheckpointError,
        TrainingProgress,
        train_cnn_model,
    )

_EXPORTS = {
    "CnnConfig": "config",
    "CubeConfig": "config",
    "NetworkConfig": "config",
    "PredictionConfig": "config",
    "TrainingConfig": "config",
    "config_from_dict": "config",
    "config_to_dict": "config",
    "load_config": "config",
    "CrossValidationResult": "crossval",
    "FoldResult": "crossval",
    "cross_validate": "crossval",
    "scan_folds": "crossval",
    "CentringError": "cubes",
    "Occupancy": "cubes",
    "build_occupancy": "cubes",
    "compute_corner_cells": "cubes",
    "compute_cubes": "cubes",
    "fill_cubes": "cubes",
    "CnnModel": "model",
    "DeviceError": "model",
    "DeepNet": "network",
    "build_network": "network",
    "count_parameters": "network",
    "ModelFileError": "persistence",
    "load_model": "persistence",
    "read_model_header": "persistence",
    "save_model": "persistence",
    "CheckpointError": "training",
    "TrainingProgress": "training",
    "train_cnn_model": "training",
}

__all__ = [
    "CentringError",
    "CheckpointError",
    "CnnConfig",
    "CnnModel",
    "CrossValidationResult",
    "CubeConfig",
    "DeepNet",
    "DeviceError",
    "FoldResult",
    "ModelFileError",
    "NetworkConfig",
    "Occupancy",
    "PredictionConfig",
    "TrainingConfig",
    "TrainingProgress",
    "build_network",
    "build_occupancy",
    "compute_corner_cells",
    "compute_cubes",
    "config_from_dict",
    "config_to_dict",
    "count_parameters",
    "cross_validate",
    "fill_cubes",
    "load_config",
    "load_model",
    "read_model_header",
    "save_model",
    "scan_folds",
    "train_cnn_model",
]

__getattr__, __dir__ = lazy_exports(
    __name__, {name: f"semantic3d.baselines.cnn.{module}" for name, module in _EXPORTS.items()}
)
