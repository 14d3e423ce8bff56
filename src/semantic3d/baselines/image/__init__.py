"""The paper's 2D image baseline: cube maps of each station, 2D segmentation, labels back to points.

Scans are rendered onto the six faces of a cube around the scanner
(:mod:`semantic3d.viz.cubemap`); the faces are segmented either after the paper's method
(dense texton, DAISY, ternary-pattern and self-similarity words, rectangle bag-of-words
features, boosting, superpixels and a CRF solved by graph cuts) or with a small U-Net
(``[torch]``, not in the paper); every point takes the class of the pixel it projects to
(a rule the paper does not describe). docs/baseline_image.md lists every difference from
the paper.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.baselines.image.config import ImageConfig, load_config, preset_config
    from semantic3d.baselines.image.model import ImageModel, ImageVariant, StationPredictor
    from semantic3d.baselines.image.persistence import load_model, read_model_header, save_model
    from semantic3d.baselines.image.predict import ImagePrediction, predict_image_scan
    from semantic3d.baselines.image.segmenter import BoostedSegmenter
    from semantic3d.baselines.image.training import train_image_model

_EXPORTS = {
    "ImageConfig": "config",
    "load_config": "config",
    "preset_config": "config",
    "ImageModel": "model",
    "ImageVariant": "model",
    "StationPredictor": "model",
    "load_model": "persistence",
    "read_model_header": "persistence",
    "save_model": "persistence",
    "ImagePrediction": "predict",
    "predict_image_scan": "predict",
    "BoostedSegmenter": "segmenter",
    "train_image_model": "training",
}

__all__ = [
    "BoostedSegmenter",
    "ImageConfig",
    "ImageModel",
    "ImagePrediction",
    "ImageVariant",
    "StationPredictor",
    "load_config",
    "load_model",
    "predict_image_scan",
    "preset_config",
    "read_model_header",
    "save_model",
    "train_image_model",
]

__getattr__, __dir__ = lazy_exports(
    __name__, {name: f"semantic3d.baselines.image.{module}" for name, module in _EXPORTS.items()}
)
