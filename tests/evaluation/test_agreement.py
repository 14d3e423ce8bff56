"""Label agreement of two overlapping scans with a known mislabelled region.

Scan A is a 0.1 m grid over x in [0, 20) m, scan B the same grid over x in [10, 30) m
shifted by (-1 cm, -1 cm): in the overlap every point has exactly one partner 1.4 cm
away, whose tile often differs (tile edges fall between partners). Ground truth is class
1 for grid columns i < 150 and class 5 beyond. A holds scanning artefacts (7) in columns
120..124; B leaves 100 points unlabelled (0) and mislabels columns 160..169 as class 3.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semantic3d.core import PointCloud
from semantic3d.core.errors import ShapeError
from semantic3d.evaluation.agreement import (
    compute_label_agreement,
    compute_label_agreement_files,
)
from semantic3d.io.ascii import write_ascii_points
from semantic3d.metrics import ConfusionMatrix
from tests.evaluation.conftest import overlapping_scans


def _expected_a_to_b() -> np.ndarray:
    matrix = np.zeros((8, 8), np.int64)
    matrix[0, 0] = 50 * 100 - 500 - 100  # class 1, minus A's artefacts and B's unlabelled
    matrix[4, 4] = 40 * 100
    matrix[2, 4] = 10 * 100  # B says high vegetation where A says buildings
    return matrix


def test_known_mislabelled_region_in_both_directions() -> None:
    a, b = overlapping_scans()
    result = compute_label_agreement([a], [b], tile_size_m=50.0)
    a_to_b, b_to_a = result.directions
    assert (a_to_b.name, b_to_a.name) == ("A→B", "B→A")
    np.testing.assert_array_equal(a_to_b.confusion, _expected_a_to_b())
    np.testing.assert_array_equal(b_to_a.confusion, _expected_a_to_b().T)
    assert (a_to_b.n_points, a_to_b.n_matched) == (20_000 - 100, 9_400)
    assert (b_to_a.n_points, b_to_a.n_matched) == (20_000 - 500, 9_400)
    # A→B: receiving labels are B's; IoU_5 = 4000 / (4000 + 1000), IoU_3 = 0
    np.testing.assert_allclose(a_to_b.scores.iou[[0, 2, 4]], [1.0, 0.0, 0.8])
    assert a_to_b.scores.mean_iou == pytest.approx(0.6)
    assert a_to_b.scores.recall[2] == 0.0 and np.isnan(a_to_b.scores.precision[2])
    assert np.isnan(b_to_a.scores.recall[2]) and b_to_a.scores.precision[2] == 0.0
    assert np.isnan(a_to_b.scores.iou[6])  # artefacts excluded
    assert result.excluded_values == (0, 7)


def test_small_tiles_and_disk_spill_change_nothing(tmp_path: Path) -> None:
    a, b = overlapping_scans()
    whole = compute_label_agreement([a], [b], tile_size_m=50.0)
    progress: list[tuple[int, int]] = []
    tiled = compute_label_agreement(
        [a[:7_000], a[7_000:]],
        [b[:333], b[333:]],
        tile_size_m=1.0,
        buffer_points=1_000,
        spill_directory=tmp_path,
        progress=lambda done, total: progress.append((done, total)),
    )
    for left, right in zip(whole.directions, tiled.directions, strict=True):
        np.testing.assert_array_equal(left.confusion, right.confusion)
        assert left.n_matched == right.n_matched
    done, total = progress[-1]
    assert done == total > 300  # 30 x 10 one-metre tiles and a row and column of B's shift
    assert list(tmp_path.iterdir()) == []  # spill folder removed


def test_distance_threshold() -> None:
    a, b = overlapping_scans()
    result = compute_label_agreement([a], [b], max_distance_m=0.01)  # partners are 1.4 cm away
    assert result.a_to_b.n_matched == result.b_to_a.n_matched == 0
    assert np.isnan(result.a_to_b.scores.mean_iou)


def test_scans_on_disk(tmp_path: Path) -> None:
    a, b = overlapping_scans()
    for name, cloud in (("a", a), ("b", b)):
        write_ascii_points(
            tmp_path / f"{name}.txt", [cloud], labels_path=tmp_path / f"{name}.labels"
        )
    result = compute_label_agreement_files(
        tmp_path / "a.txt", tmp_path / "a.labels", tmp_path / "b.txt", tmp_path / "b.labels"
    )
    np.testing.assert_array_equal(result.a_to_b.confusion, _expected_a_to_b())


def test_bad_input() -> None:
    a, b = overlapping_scans()
    with pytest.raises(ShapeError, match="scan A: expected labelled points"):
        compute_label_agreement([a.with_labels(None)], [b])
    labels = np.asarray(b.labels).copy()
    labels[3] = 9
    with pytest.raises(ShapeError, match=r"scan B: expected label values 0\.\.8, found 9"):
        compute_label_agreement([a], [b.with_labels(labels)])
    with pytest.raises(ValueError, match="max_distance_m: expected a positive distance"):
        compute_label_agreement([a], [b], max_distance_m=0.0)


def test_distance_wider_than_a_tile_reads_several_rings_of_neighbours() -> None:
    a, b = overlapping_scans()
    # A 4 m strip across the overlap keeps the ~2,000 tiny tiles few enough to be quick.
    a = a[(a.xyz[:, 0] > 8.0) & (a.xyz[:, 0] < 12.0)]
    b = b[(b.xyz[:, 0] > 8.0) & (b.xyz[:, 0] < 12.0)]
    wide = compute_label_agreement([a], [b], max_distance_m=0.3, tile_size_m=0.2)
    whole = compute_label_agreement([a], [b], max_distance_m=0.3, tile_size_m=100.0)
    assert whole.a_to_b.n_matched > 1_000
    for tiled, untiled in zip(wide.directions, whole.directions, strict=True):
        np.testing.assert_array_equal(tiled.confusion, untiled.confusion)
        assert tiled.n_matched == untiled.n_matched


def _reference(
    receiver: PointCloud, source: PointCloud, max_distance_m: float, *, exclude_first: bool
) -> tuple[np.ndarray, int]:
    """One untiled cKDTree over the whole source scan: the textbook transfer.

    The default order searches among all source points and leaves out the pairs whose
    source point is unlabelled or an artefact; ``exclude_first`` removes those first.
    """
    from scipy.spatial import cKDTree

    keep_r = ~np.isin(np.asarray(receiver.labels), (0, 7))
    keep_s = ~np.isin(np.asarray(source.labels), (0, 7))
    if not exclude_first:
        keep_s[:] = True
    distance, index = cKDTree(source.xyz[keep_s]).query(
        receiver.xyz[keep_r], k=1, distance_upper_bound=max_distance_m
    )
    hit = np.isfinite(distance)
    taken = np.zeros(hit.size, np.uint8)
    taken[hit] = np.asarray(source.labels)[keep_s][index[hit]]
    hit &= ~np.isin(taken, (0, 7))
    matrix = ConfusionMatrix()
    matrix.update(np.asarray(receiver.labels)[keep_r][hit], taken[hit])
    return matrix.compute(), int(hit.sum())


@pytest.mark.parametrize("exclude_first", [False, True], ids=["paper_order", "exclude_first"])
@pytest.mark.parametrize("tile_size_m", [0.7, 3.0, 50.0])
def test_equals_an_untiled_nearest_neighbour_search(
    tile_size_m: float, exclude_first: bool
) -> None:
    # Clustered points (dense blobs and sparse outskirts, as scans near and far from a
    # station), so the occupancy filter both keeps and drops points.
    rng = np.random.default_rng(4)
    scene = rng.uniform(0.0, 1.5, (40, 3))  # blob centres both scans see

    def scan(offset: float) -> PointCloud:
        centres = scene + np.array([offset, 0.0, 0.0])
        n = 30_000
        spread = np.where(rng.random(n) < 0.5, 0.02, 0.3)[:, None]
        xyz = centres[rng.integers(0, 40, n)] + rng.normal(0.0, 1.0, (n, 3)) * spread
        return PointCloud.from_arrays(xyz, labels=rng.integers(0, 9, n).astype(np.uint8))

    a, b = scan(0.0), scan(0.01)
    result = compute_label_agreement(
        [a], [b], max_distance_m=0.04, tile_size_m=tile_size_m,
        exclude_before_matching=exclude_first,
    )  # fmt: skip
    assert result.excluded_before_matching is exclude_first
    for direction, (receiver, source) in zip(result.directions, ((b, a), (a, b)), strict=True):
        matrix, n_matched = _reference(receiver, source, 0.04, exclude_first=exclude_first)
        assert 1_000 < n_matched < 25_000
        assert direction.n_matched == n_matched
        np.testing.assert_array_equal(direction.confusion, matrix)


def test_an_artefact_nearer_than_a_partner_hides_the_partner_in_the_paper_order() -> None:
    """B's point has an artefact of A 1 cm away and a building point of A 3 cm away."""
    a = PointCloud.from_arrays([[0.01, 0.0, 0.0], [0.03, 0.0, 0.0]], labels=[7, 5])
    b = PointCloud.from_arrays([[0.0, 0.0, 0.0]], labels=[5])
    paper = compute_label_agreement([a], [b])
    first = compute_label_agreement([a], [b], exclude_before_matching=True)
    assert paper.a_to_b.n_points == first.a_to_b.n_points == 1
    assert paper.a_to_b.n_matched == 0  # its nearest neighbour is an artefact: left out
    assert first.a_to_b.n_matched == 1 and first.a_to_b.confusion[4, 4] == 1
