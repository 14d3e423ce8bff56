"""The 3D covariance baseline (Hackel, Wegner & Schindler 2016): multi-scale covariance
features and a random forest, trained class-balanced and applied to whole scans in
bounded memory. See docs/baseline_covariance.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.baselines.covariance.config import (
        CovarianceConfig,
        ForestConfig,
        GridSearchConfig,
        PredictionConfig,
        SamplingConfig,
        config_from_dict,
        config_to_dict,
        load_config,
    )
    from semantic3d.baselines.covariance.estimator import CovarianceClassifier
    from semantic3d.baselines.covariance.model import CovarianceModel, GridSearchResult
    from semantic3d.baselines.covariance.persistence import (
        ModelFileError,
        load_model,
        read_model_header,
        save_model,
    )
    from semantic3d.baselines.covariance.predict import (
        HardwareInfo,
        PredictionRun,
        PredictionRunSet,
        describe_hardware,
        predict_cloud,
        predict_scan,
        predict_scans,
    )
    from semantic3d.baselines.covariance.training import (
        LabelledScan,
        TrainingDataError,
        TrainingSet,
        build_training_set,
        find_labelled_scans,
        fit_model,
        run_grid_search,
        sample_training_points,
        train_covariance_model,
    )

__all__ = [
    "CovarianceClassifier",
    "CovarianceConfig",
    "CovarianceModel",
    "ForestConfig",
    "GridSearchConfig",
    "GridSearchResult",
    "HardwareInfo",
    "LabelledScan",
    "ModelFileError",
    "PredictionConfig",
    "PredictionRun",
    "PredictionRunSet",
    "SamplingConfig",
    "TrainingDataError",
    "TrainingSet",
    "build_training_set",
    "config_from_dict",
    "config_to_dict",
    "describe_hardware",
    "find_labelled_scans",
    "fit_model",
    "load_config",
    "load_model",
    "predict_cloud",
    "predict_scan",
    "predict_scans",
    "read_model_header",
    "run_grid_search",
    "sample_training_points",
    "save_model",
    "train_covariance_model",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "CovarianceClassifier": "semantic3d.baselines.covariance.estimator",
        "CovarianceConfig": "semantic3d.baselines.covariance.config",
        "CovarianceModel": "semantic3d.baselines.covariance.model",
        "ForestConfig": "semantic3d.baselines.covariance.config",
        "GridSearchConfig": "semantic3d.baselines.covariance.config",
        "GridSearchResult": "semantic3d.baselines.covariance.model",
        "HardwareInfo": "semantic3d.baselines.covariance.predict",
        "LabelledScan": "semantic3d.baselines.covariance.training",
        "ModelFileError": "semantic3d.baselines.covariance.persistence",
        "PredictionConfig": "semantic3d.baselines.covariance.config",
        "PredictionRun": "semantic3d.baselines.covariance.predict",
        "PredictionRunSet": "semantic3d.baselines.covariance.predict",
        "SamplingConfig": "semantic3d.baselines.covariance.config",
        "TrainingDataError": "semantic3d.baselines.covariance.training",
        "TrainingSet": "semantic3d.baselines.covariance.training",
        "build_training_set": "semantic3d.baselines.covariance.training",
        "config_from_dict": "semantic3d.baselines.covariance.config",
        "config_to_dict": "semantic3d.baselines.covariance.config",
        "describe_hardware": "semantic3d.baselines.covariance.predict",
        "find_labelled_scans": "semantic3d.baselines.covariance.training",
        "fit_model": "semantic3d.baselines.covariance.training",
        "load_config": "semantic3d.baselines.covariance.config",
        "load_model": "semantic3d.baselines.covariance.persistence",
        "predict_cloud": "semantic3d.baselines.covariance.predict",
        "predict_scan": "semantic3d.baselines.covariance.predict",
        "predict_scans": "semantic3d.baselines.covariance.predict",
        "read_model_header": "semantic3d.baselines.covariance.persistence",
        "run_grid_search": "semantic3d.baselines.covariance.training",
        "sample_training_points": "semantic3d.baselines.covariance.training",
        "save_model": "semantic3d.baselines.covariance.persistence",
        "train_covariance_model": "semantic3d.baselines.covariance.training",
    },
)
