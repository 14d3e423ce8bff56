"""The 3D covariance baseline (Hackel, Wegner & Schindler 2016): multi-scale covariance
features and a random forest, trained class-balanced and applied to whole scans in
bounded memory. See docs/baseline_covariance.md.
"""

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
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.baselines.covariance.persistence import (
    ModelFileError,
    load_model,
    read_model_header,
    save_model,
)
from semantic3d.baselines.covariance.predict import (
    HardwareInfo,
    PredictionRun,
    describe_hardware,
    predict_cloud,
    predict_scan,
)
from semantic3d.baselines.covariance.training import (
    GridSearchResult,
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
    "read_model_header",
    "run_grid_search",
    "sample_training_points",
    "save_model",
    "train_covariance_model",
]
