"""Visual words and rectangle bag-of-words features through integral images.

:class:`Vocabulary` clusters each continuous descriptor kind (standardised) with
scikit-learn's MiniBatchKMeans into ``n_words`` words; ternary-pattern codes are words
already. :class:`RectangleFeatures` are TextonBoost's shape filters: a random rectangle
(corners within ``max_offset_px`` of the pixel) and a word; the feature is the share of
the rectangle's pixels showing that word, read in four look-ups from the word's integral
image, so every feature costs the same whatever the rectangle's size.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.image.features import CODE_KINDS, CONTINUOUS_KINDS, Descriptors
from semantic3d.core.errors import require

__all__ = ["RectangleFeatures", "Vocabulary", "WordMaps"]

WordMaps = dict[str, NDArray[np.int16]]
"""Descriptor kind -> ``(h, w)`` word of each pixel."""

_N_CODES = 256


@dataclass(frozen=True, slots=True)
class Vocabulary:
    """Fitted words of every continuous descriptor kind.

    Attributes:
        n_words: words per continuous kind.
        means, scales: per kind, the standardisation applied before clustering.
        kmeans: per kind, the fitted ``MiniBatchKMeans``.
    """

    n_words: int
    means: dict[str, NDArray[np.float32]]
    scales: dict[str, NDArray[np.float32]]
    kmeans: dict[str, Any]

    @classmethod
    def fit(
        cls,
        descriptors: Sequence[Descriptors],
        masks: Sequence[NDArray[np.bool_]],
        *,
        n_words: int,
        sample_pixels: int,
        seed: int,
        progress: Callable[[int, int], None] | None = None,
    ) -> Vocabulary:
        """Cluster ``sample_pixels`` pixels (within ``masks``) of each kind into words;
        ``progress(kinds_done, n_kinds)`` after each kind."""
        cluster = require("sklearn.cluster", "image")
        rng = np.random.default_rng(seed)
        means: dict[str, NDArray[np.float32]] = {}
        scales: dict[str, NDArray[np.float32]] = {}
        fitted: dict[str, Any] = {}
        per_image = max(sample_pixels // max(len(descriptors), 1), 1)
        for number, kind in enumerate(CONTINUOUS_KINDS):
            rows = []
            for desc, mask in zip(descriptors, masks, strict=True):
                values = desc.continuous[kind][mask]
                if values.shape[0] > per_image:
                    values = values[rng.choice(values.shape[0], per_image, replace=False)]
                rows.append(values)
            sample = np.concatenate(rows).astype(np.float32)
            mean = sample.mean(axis=0)
            scale = np.maximum(sample.std(axis=0), 1e-6)
            words = min(n_words, max(sample.shape[0], 1))
            kmeans = cluster.MiniBatchKMeans(  # type: ignore[attr-defined]
                n_clusters=words, random_state=seed, batch_size=4096, n_init=3
            )
            kmeans.fit((sample - mean) / scale)
            means[kind], scales[kind], fitted[kind] = mean, scale.astype(np.float32), kmeans
            if progress is not None:
                progress(number + 1, len(CONTINUOUS_KINDS))
        return cls(n_words, means, scales, fitted)

    def n_words_of(self, kind: str) -> int:
        """Words of a kind."""
        return _N_CODES if kind in CODE_KINDS else int(self.kmeans[kind].n_clusters)

    def words(self, descriptors: Descriptors) -> WordMaps:
        """The word of every pixel, per kind."""
        maps: WordMaps = dict(descriptors.codes)
        for kind in CONTINUOUS_KINDS:
            values = descriptors.continuous[kind]
            height, width, depth = values.shape
            flat = (values.reshape(-1, depth) - self.means[kind]) / self.scales[kind]
            maps[kind] = self.kmeans[kind].predict(flat).astype(np.int16).reshape(height, width)
        return maps


@dataclass(frozen=True, slots=True)
class RectangleFeatures:
    """Random (rectangle, kind, word) features.

    Attributes:
        kinds: descriptor kind of each feature.
        words: word of each feature.
        boxes: ``(n, 4)`` int32 ``(row0, col0, row1, col1)`` offsets from the pixel,
            half-open (``row0 < row1``, ``col0 < col1``).
    """

    kinds: tuple[str, ...]
    words: NDArray[np.int32]
    boxes: NDArray[np.int32]

    @classmethod
    def sample(
        cls, vocabulary: Vocabulary, *, n_rectangles: int, max_offset_px: int, seed: int
    ) -> RectangleFeatures:
        """``n_rectangles`` random rectangles, each paired with one random word of every kind."""
        rng = np.random.default_rng(seed)
        kinds: list[str] = []
        words: list[int] = []
        boxes: list[tuple[int, int, int, int]] = []
        for _ in range(n_rectangles):
            corners = rng.integers(-max_offset_px, max_offset_px + 1, size=(2, 2))
            row0, row1 = sorted(int(v) for v in corners[:, 0])
            col0, col1 = sorted(int(v) for v in corners[:, 1])
            box = (row0, col0, row1 + 1, col1 + 1)
            for kind in (*CONTINUOUS_KINDS, *CODE_KINDS):
                kinds.append(kind)
                words.append(int(rng.integers(0, vocabulary.n_words_of(kind))))
                boxes.append(box)
        return cls(tuple(kinds), np.asarray(words, np.int32), np.asarray(boxes, np.int32))

    @property
    def names(self) -> tuple[str, ...]:
        """Feature names: ``kind:word@row0,col0,row1,col1``."""
        return tuple(
            f"{kind}:{word}@{','.join(str(v) for v in box)}"
            for kind, word, box in zip(self.kinds, self.words, self.boxes, strict=True)
        )

    def compute(
        self,
        word_maps: WordMaps,
        rows: NDArray[np.int64],
        cols: NDArray[np.int64],
    ) -> NDArray[np.float32]:
        """``(len(rows), n_features)``: each feature at pixels ``(rows, cols)``."""
        height, width = next(iter(word_maps.values())).shape
        out = np.empty((rows.size, len(self.kinds)), np.float32)
        order: dict[tuple[str, int], list[int]] = {}
        for number, (kind, word) in enumerate(zip(self.kinds, self.words, strict=True)):
            order.setdefault((kind, int(word)), []).append(number)
        for (kind, word), numbers in order.items():
            integral = np.zeros((height + 1, width + 1), np.float32)
            integral[1:, 1:] = np.cumsum(np.cumsum(word_maps[kind] == word, axis=0), axis=1)
            for number in numbers:
                row0, col0, row1, col1 = self.boxes[number]
                r0 = np.clip(rows + row0, 0, height)
                r1 = np.clip(rows + row1, 0, height)
                c0 = np.clip(cols + col0, 0, width)
                c1 = np.clip(cols + col1, 0, width)
                count = integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]
                area = np.maximum((r1 - r0) * (c1 - c0), 1)
                out[:, number] = count / area
        return out
