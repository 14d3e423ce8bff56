"""The paper's image classifier: words, rectangle features, boosting, superpixels, a CRF.

:class:`BoostedSegmenter` follows associative hierarchical fields (Ladický et al.) in
structure, with the differences docs/baseline_image.md lists (DAISY where the paper has
SIFT; superpixel potentials from the pixels' posteriors, with no superpixel classifier of
their own): dense texton, DAISY, ternary-pattern and self-similarity descriptors
(:mod:`~semantic3d.baselines.image.features`), k-means words, rectangle bag-of-words
features through integral images (:mod:`~semantic3d.baselines.image.words`), a boosted
classifier (scikit-learn's HistGradientBoostingClassifier, class-balanced), and a CRF with
pixel and superpixel potentials solved by alpha-expansion (:mod:`~semantic3d.baselines.image.crf`).
It is a scikit-learn-style estimator: ``fit`` returns self, fitted attributes end in ``_``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.image.config import ImageConfig
from semantic3d.baselines.image.crf import (
    alpha_expansion,
    compute_superpixels,
    contrast_weights,
    superpixel_unary,
)
from semantic3d.baselines.image.faces import Face
from semantic3d.baselines.image.features import Descriptors, compute_descriptors
from semantic3d.baselines.image.words import RectangleFeatures, Vocabulary, WordMaps
from semantic3d.core.errors import require

__all__ = ["BoostedSegmenter"]

_BLOCK_PIXELS = 16_384
_BOOSTING_STEP = 10
"""Boosting rounds fitted between two progress reports."""


class BoostedSegmenter:
    """Pixel classifier + CRF on cube faces; classes are label values (class 7 excluded)."""

    def __init__(self, config: ImageConfig) -> None:
        self.config = config

    def _descriptors(self, face: Face) -> Descriptors:
        words = self.config.words
        return compute_descriptors(
            face.rgb,
            daisy_step=words.daisy_step,
            daisy_radius=words.daisy_radius,
            ltp_threshold=words.ltp_threshold,
        )

    def _features(
        self,
        descriptors: Descriptors,
        word_maps: WordMaps,
        face: Face,
        rows: NDArray[np.int64],
        cols: NDArray[np.int64],
    ) -> NDArray[np.float32]:
        values = self.rectangles_.compute(word_maps, rows, cols)
        if not self.config.rectangles.location:
            return values
        location = np.column_stack(
            [face.elevation[rows, cols], descriptors.lab[rows, cols]]
        ).astype(np.float32)
        return np.concatenate([values, location], axis=1)

    def fit(
        self, faces: Sequence[Face], *, progress: Callable[[str, int, int], None] | None = None
    ) -> BoostedSegmenter:
        """Fit words, rectangles and the boosted classifier on labelled faces.

        Raises:
            ValueError: fewer than two classes among the labelled pixels.
        """
        ensemble = require("sklearn.ensemble", "image")
        config = self.config
        rng = np.random.default_rng(config.seed)
        usable = [f for f in faces if f.labels is not None and f.valid.any()]
        descriptors = []
        for number, face in enumerate(usable):
            descriptors.append(self._descriptors(face))
            if progress is not None:
                progress("descriptors", number + 1, len(usable))
        self.vocabulary_ = Vocabulary.fit(
            descriptors,
            [f.valid for f in usable],
            n_words=config.words.n_words,
            sample_pixels=config.words.sample_pixels,
            seed=config.seed,
            progress=None if progress is None else partial(progress, "words"),
        )
        self.rectangles_ = RectangleFeatures.sample(
            self.vocabulary_,
            n_rectangles=config.rectangles.n_rectangles,
            max_offset_px=config.rectangles.max_offset_px,
            seed=config.seed,
        )
        rows_x: list[NDArray[np.float32]] = []
        rows_y: list[NDArray[np.uint8]] = []
        per_class = config.boosting.pixels_per_class_per_face
        for number, (face, desc) in enumerate(zip(usable, descriptors, strict=True)):
            assert face.labels is not None
            word_maps = self.vocabulary_.words(desc)
            picked = []
            for value in np.unique(face.labels[face.labels > 0]):
                where = np.flatnonzero(face.labels.reshape(-1) == value)
                if where.size > per_class:
                    where = rng.choice(where, per_class, replace=False)
                picked.append(where)
            if not picked:
                continue
            flat = np.sort(np.concatenate(picked))
            rows, cols = np.divmod(flat, face.labels.shape[1])
            rows_x.append(self._features(desc, word_maps, face, rows, cols))
            rows_y.append(face.labels.reshape(-1)[flat])
            if progress is not None:
                progress("features", number + 1, len(usable))
        y = np.concatenate(rows_y) if rows_y else np.empty(0, np.uint8)
        if np.unique(y).size < 2:
            raise ValueError(
                f"training faces: expected labelled pixels of at least 2 classes, found "
                f"{np.unique(y).tolist()}"
            )
        booster = ensemble.HistGradientBoostingClassifier(  # type: ignore[attr-defined]
            max_iter=config.boosting.max_iter,
            learning_rate=config.boosting.learning_rate,
            max_leaf_nodes=config.boosting.max_leaf_nodes,
            class_weight="balanced",
            early_stopping=False,
            random_state=config.seed,
            warm_start=True,
        )
        x = np.concatenate(rows_x)
        # Rounds are added _BOOSTING_STEP at a time (warm start) to report progress: without
        # early stopping, and with a fixed seed for the binning, the trees are the same as
        # those of one fit (tests/baselines/image).
        total = config.boosting.max_iter
        for rounds in range(min(_BOOSTING_STEP, total), total + _BOOSTING_STEP, _BOOSTING_STEP):
            booster.set_params(max_iter=min(rounds, total))
            booster.fit(x, y)
            if progress is not None:
                progress("boosting", booster.n_iter_, total)
        self.booster_: Any = booster
        self.classes_ = np.asarray(booster.classes_, np.uint8)
        self.n_training_pixels_ = int(y.size)
        return self

    def predict_proba(self, face: Face) -> NDArray[np.float32]:
        """``(s, s, n_classes)`` posteriors of the boosted classifier (no CRF)."""
        desc = self._descriptors(face)
        return self._proba(face, desc, self.vocabulary_.words(desc))

    def _proba(self, face: Face, desc: Descriptors, word_maps: WordMaps) -> NDArray[np.float32]:
        height, width = face.valid.shape
        out = np.empty((height * width, self.classes_.size), np.float32)
        for begin in range(0, height * width, _BLOCK_PIXELS):
            flat = np.arange(begin, min(begin + _BLOCK_PIXELS, height * width))
            rows, cols = np.divmod(flat, width)
            out[flat] = self.booster_.predict_proba(
                self._features(desc, word_maps, face, rows, cols)
            )
        return out.reshape(height, width, -1)

    def segment(self, face: Face) -> NDArray[np.uint8]:
        """``(s, s)`` label values after the CRF (0 where no point is shown)."""
        config = self.config
        desc = self._descriptors(face)
        proba = self._proba(face, desc, self.vocabulary_.words(desc))
        unary = -np.log(proba + 1e-6)
        levels = compute_superpixels(
            face.rgb,
            method=config.superpixels.method,
            scales=config.superpixels.scales,
            seed=config.seed,
        )
        share = config.crf.superpixel_weight / max(len(levels), 1)
        for segments in levels:
            unary += share * superpixel_unary(proba, segments)
        unary[~face.valid] = 0.0
        horizontal, vertical = contrast_weights(desc.lab, weight=config.crf.pairwise_weight)
        classes = alpha_expansion(
            unary.astype(np.float32), horizontal, vertical, n_cycles=config.crf.n_cycles
        )
        labels = self.classes_[classes]
        labels[~face.valid] = 0
        return labels
