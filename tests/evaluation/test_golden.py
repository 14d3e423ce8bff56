"""Golden numbers: a fixed synthetic submission whose scores were computed by hand.

The confusion matrix below (rows ground truth 1..8, columns prediction 1..8) is realised
as two scans with shuffled lines, unlabelled points, CRLF line ends in one file and a
top-level folder in the zip. Class 7 is absent from truth and prediction.

    IoU_1 =  90 / (100 + 115 -  90) =  90 / 125
    IoU_2 =  80 / (100 +  90 -  80) =  80 / 110
    IoU_3 =  70 / (100 +  80 -  70) =  70 / 110
    IoU_4 =  40 / ( 50 +  70 -  40) =  40 /  80
    IoU_5 = 200 / (200 + 215 - 200) = 200 / 215
    IoU_6 =  30 / ( 50 +  40 -  30) =  30 /  60
    IoU_7 = absent (NaN, left out of the mean)
    IoU_8 =  10 / ( 20 +  10 -  10) =  10 /  20
    OA    = 520 / 620
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from semantic3d.evaluation import (
    EvaluationResult,
    MethodInfo,
    custom_challenge,
    evaluate_submission,
)
from tests.evaluation.conftest import labels_bytes, write_zip

MATRIX = np.array(
    [
        [90, 10, 0, 0, 0, 0, 0, 0],
        [20, 80, 0, 0, 0, 0, 0, 0],
        [0, 0, 70, 30, 0, 0, 0, 0],
        [0, 0, 10, 40, 0, 0, 0, 0],
        [0, 0, 0, 0, 200, 0, 0, 0],
        [5, 0, 0, 0, 15, 30, 0, 0],
        [0, 0, 0, 0, 0, 0, 0, 0],
        [0, 0, 0, 0, 0, 10, 0, 10],
    ]
)
GOLDEN_IOU = [90 / 125, 80 / 110, 70 / 110, 40 / 80, 200 / 215, 30 / 60, math.nan, 10 / 20]
GOLDEN_MEAN_IOU = 0.644838417396557  # (2.22 + 15/11 + 40/43) / 7: the 7 present IoUs
GOLDEN_OA = 520 / 620


def _pairs() -> tuple[np.ndarray, np.ndarray]:
    truth, pred = [], []
    for i in range(8):
        for j in range(8):
            truth += [i + 1] * int(MATRIX[i, j])
            pred += [j + 1] * int(MATRIX[i, j])
    truth += [0] * 37  # unlabelled points, predicted anything: ignored
    pred += [(k % 8) + 1 for k in range(37)]
    order = np.random.default_rng(2017).permutation(len(truth))
    return np.array(truth)[order], np.array(pred)[order]


@pytest.fixture
def golden(tmp_path: Path) -> tuple[Path, Path]:
    truth, pred = _pairs()
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    cut = 250
    (gt_dir / "scan_a.labels").write_bytes(labels_bytes(truth[:cut]))
    (gt_dir / "scan_b.labels").write_bytes(labels_bytes(truth[cut:]))
    members = {
        "submission/scan_a.labels": labels_bytes(pred[:cut], crlf=True),
        "submission/scan_b.labels": labels_bytes(pred[cut:]),
        "__MACOSX/submission/._scan_a.labels": b"resource fork",
    }
    return gt_dir, write_zip(tmp_path / "golden.zip", members)


def test_golden_mean_iou_is_the_mean_of_the_present_classes() -> None:
    assert pytest.approx(np.nanmean(GOLDEN_IOU), abs=1e-15) == GOLDEN_MEAN_IOU


def test_golden_numbers(golden: tuple[Path, Path]) -> None:
    gt_dir, submission = golden
    result = evaluate_submission(
        submission,
        challenge=custom_challenge(gt_dir, name="golden"),
        method=MethodInfo("golden method", runtime_s=12.5),
        chunk_size=64,
    )
    np.testing.assert_array_equal(result.confusion, MATRIX)
    np.testing.assert_allclose(result.scores.iou, GOLDEN_IOU, rtol=0, atol=1e-12)
    assert result.scores.mean_iou == pytest.approx(GOLDEN_MEAN_IOU, abs=1e-12)
    assert result.scores.overall_accuracy == pytest.approx(GOLDEN_OA, abs=1e-12)
    assert result.n_points == 620
    assert result.scores.absent_indices == (6,)
    assert result.challenge == "golden"
    assert result.protocol_version == "1"
    assert [scan.name for scan in result.per_scan] == ["scan_a", "scan_b"]
    assert sum(scan.n_points for scan in result.per_scan) == 620
    np.testing.assert_array_equal(sum(scan.confusion for scan in result.per_scan), MATRIX)


def test_golden_json_round_trip(golden: tuple[Path, Path]) -> None:
    gt_dir, submission = golden
    result = evaluate_submission(submission, challenge=custom_challenge(gt_dir, name="golden"))
    text = json.dumps(result.to_dict(), allow_nan=False)
    data = json.loads(text)
    assert data["scores"]["iou"][6] is None
    assert data["scores"]["absent"] == ["scanning artefacts"]
    assert data["scores"]["mean_iou"] == pytest.approx(GOLDEN_MEAN_IOU, abs=1e-12)
    loaded = EvaluationResult.from_dict(data)
    np.testing.assert_array_equal(loaded.confusion, MATRIX)
    np.testing.assert_allclose(loaded.scores.iou, GOLDEN_IOU, atol=1e-12)
    assert [s.name for s in loaded.per_scan] == ["scan_a", "scan_b"]
    assert "per_scan" not in result.to_public_dict()
