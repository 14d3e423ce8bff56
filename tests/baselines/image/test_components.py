"""Image baseline pieces: CRF solver, rectangle features, descriptors, configuration."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from semantic3d.baselines.image.config import (
    ImageConfig,
    config_from_dict,
    load_config,
    preset_config,
)
from semantic3d.baselines.image.crf import alpha_expansion, grid_energy, superpixel_unary
from semantic3d.baselines.image.faces import labels_through_index
from semantic3d.baselines.image.features import compute_ltp
from semantic3d.baselines.image.words import RectangleFeatures
from semantic3d.core.errors import ConfigError


def _problem(seed: int, shape: tuple[int, int], n_labels: int):
    rng = np.random.default_rng(seed)
    unary = rng.uniform(0, 2, (*shape, n_labels)).astype(np.float32)
    horizontal = rng.uniform(0, 1.5, (shape[0], shape[1] - 1)).astype(np.float32)
    vertical = rng.uniform(0, 1.5, (shape[0] - 1, shape[1])).astype(np.float32)
    return unary, horizontal, vertical


@pytest.mark.parametrize("seed", range(4))
def test_alpha_expansion_is_exact_for_two_labels(seed: int) -> None:
    unary, horizontal, vertical = _problem(seed, (3, 3), 2)
    found = alpha_expansion(unary, horizontal, vertical, n_cycles=3)
    best = min(
        grid_energy(np.array(bits).reshape(3, 3), unary, horizontal, vertical)
        for bits in itertools.product((0, 1), repeat=9)
    )
    assert grid_energy(found, unary, horizontal, vertical) == pytest.approx(best, rel=1e-5)


def test_alpha_expansion_lowers_the_energy_of_many_labels() -> None:
    unary, horizontal, vertical = _problem(7, (12, 10), 4)
    found = alpha_expansion(unary, horizontal, vertical, n_cycles=3)
    start = np.argmin(unary, axis=-1)
    assert grid_energy(found, unary, horizontal, vertical) < grid_energy(
        start, unary, horizontal, vertical
    )
    # Within 2x of the optimum is what alpha-expansion guarantees for Potts; a local
    # check: no single pixel change lowers the energy.
    energy = grid_energy(found, unary, horizontal, vertical)
    for r, c, label in itertools.product(range(12), range(10), range(4)):
        moved = found.copy()
        moved[r, c] = label
        assert grid_energy(moved, unary, horizontal, vertical) >= energy - 1e-4


def test_superpixel_unary_is_the_mean_posterior_of_the_segment() -> None:
    proba = np.array([[[0.8, 0.2], [0.4, 0.6]], [[0.5, 0.5], [0.5, 0.5]]], np.float32)
    segments = np.array([[0, 0], [1, 1]])
    unary = superpixel_unary(proba, segments)
    np.testing.assert_allclose(np.exp(-unary[0, 1]), [0.6, 0.4], atol=1e-5)
    np.testing.assert_allclose(np.exp(-unary[1, 0]), [0.5, 0.5], atol=1e-5)


class _Vocabulary:
    def n_words_of(self, kind: str) -> int:
        return 3


def test_rectangle_features_equal_brute_force_shares() -> None:
    rng = np.random.default_rng(1)
    maps = {
        kind: rng.integers(0, 3, (9, 11)).astype(np.int16)
        for kind in ("texton", "sift", "selfsim", "ltp_upper", "ltp_lower")
    }
    features = RectangleFeatures.sample(_Vocabulary(), n_rectangles=6, max_offset_px=4, seed=2)  # type: ignore[arg-type]
    rows, cols = np.indices((9, 11))
    values = features.compute(maps, rows.reshape(-1), cols.reshape(-1))
    for number, (kind, word, box) in enumerate(
        zip(features.kinds, features.words, features.boxes, strict=True)
    ):
        for pixel, (r, c) in enumerate(zip(rows.reshape(-1), cols.reshape(-1), strict=True)):
            r0, r1 = np.clip([r + box[0], r + box[2]], 0, 9)
            c0, c1 = np.clip([c + box[1], c + box[3]], 0, 11)
            window = maps[kind][r0:r1, c0:c1]
            expected = (window == word).sum() / max(window.size, 1)
            assert values[pixel, number] == pytest.approx(expected)


def test_ternary_patterns() -> None:
    gray = np.array([[10, 10, 10], [10, 10, 30], [0, 10, 10]], float)
    upper, lower = compute_ltp(gray, threshold=5)
    assert upper[1, 1] == 1 << 3  # the right neighbour is brighter
    assert lower[1, 1] == 1 << 6  # the lower-left neighbour is darker


def test_labels_through_index_streams_in_scan_order() -> None:
    index = np.array([[[3, -1], [0, 5]]])
    labels = np.array([1, 2, 3, 4, 5, 6], np.uint8)
    faces = labels_through_index(index, [labels[:2], labels[2:4], labels[4:]])
    assert faces.tolist() == [[[4, 0], [1, 6]]]


def test_presets_and_files(tmp_path: Path) -> None:
    assert ImageConfig().words.n_words == 512 and ImageConfig().rectangles.n_rectangles == 200
    small = preset_config("small")
    assert small.preset == "small" and small.words.n_words == 16
    path = tmp_path / "c.toml"
    path.write_text('preset = "small"\nseed = 3\n[words]\nn_words = 8\n')
    loaded = load_config(path)
    assert (loaded.seed, loaded.words.n_words, loaded.faces.size) == (3, 8, 128)
    with pytest.raises(ConfigError, match="preset: expected one of"):
        config_from_dict({"preset": "huge"})
    with pytest.raises(ConfigError, match="words"):
        config_from_dict({"words": {"n_wordz": 3}})
    with pytest.raises(ConfigError, match="method: expected one of"):
        config_from_dict({"superpixels": {"method": "watershed"}})
