"""evaluate_submission: streaming equals one-shot, sklearn reference, every problem at once."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from sklearn.metrics import confusion_matrix

from semantic3d.core.errors import DataFormatError, SubmissionError
from semantic3d.evaluation import (
    MissingGroundTruthError,
    custom_challenge,
    evaluate_submission,
    load_challenge,
)
from semantic3d.io.labels import read_labels
from tests.evaluation.conftest import Scans, labels_bytes, write_zip


def _reference(truth: np.ndarray, pred: np.ndarray) -> np.ndarray:
    keep = truth > 0
    return confusion_matrix(truth[keep], pred[keep], labels=np.arange(1, 9))


@pytest.mark.parametrize("chunk_size", [1, 7, 64, 1 << 20])
def test_streaming_equals_one_shot_sklearn(scans: Scans, tmp_path: Path, chunk_size: int) -> None:
    result = evaluate_submission(
        write_zip(tmp_path / "s.zip", scans.pred_members()),
        challenge=custom_challenge(scans.gt_dir),
        chunk_size=chunk_size,
    )
    truth = np.concatenate([scans.truth[n] for n in sorted(scans.truth)])
    pred = np.concatenate([scans.pred[n] for n in sorted(scans.pred)])
    np.testing.assert_array_equal(result.confusion, _reference(truth, pred))
    for scan in result.per_scan:
        expected = _reference(scans.truth[scan.submission_name], scans.pred[scan.submission_name])
        np.testing.assert_array_equal(scan.confusion, expected)


def test_zip_and_folder_give_the_same_result(scans: Scans, tmp_path: Path) -> None:
    challenge = custom_challenge(scans.gt_dir)
    from_zip = evaluate_submission(
        write_zip(tmp_path / "s.zip", scans.pred_members()), challenge=challenge
    )
    from_folder = evaluate_submission(scans.pred_folder(tmp_path / "s"), challenge=challenge)
    assert from_zip.to_dict() == from_folder.to_dict()


def test_progress_ends_at_the_ground_truth_size(scans: Scans, tmp_path: Path) -> None:
    calls: list[tuple[int, int]] = []
    evaluate_submission(
        scans.pred_folder(tmp_path / "s"),
        challenge=custom_challenge(scans.gt_dir),
        chunk_size=16,
        progress=lambda done, total: calls.append((done, total)),
    )
    total = sum(p.stat().st_size for p in scans.gt_dir.iterdir())
    assert calls[-1] == (total, total)
    assert all(a[0] <= b[0] for a, b in itertools.pairwise(calls))


def test_problems_of_every_scan_are_reported_together(scans: Scans, tmp_path: Path) -> None:
    alpha = scans.pred["alpha.labels"].copy()
    alpha[10] = 0
    members = {
        "alpha.labels": labels_bytes(alpha),
        "beta.labels": labels_bytes(scans.pred["beta.labels"][:-3]),
        "gamma.labels": b"1\n",
    }
    with pytest.raises(SubmissionError) as caught:
        evaluate_submission(
            write_zip(tmp_path / "s.zip", members), challenge=custom_challenge(scans.gt_dir)
        )
    assert caught.value.problems == (
        "unexpected file 'gamma.labels'",
        "alpha.labels: line 11: expected an integer label value 1..8, found 0",
        "beta.labels: expected 80 lines (one per point of the scan), found 77",
    )


def test_prediction_longer_than_the_ground_truth(scans: Scans, tmp_path: Path) -> None:
    members = scans.pred_members()
    members["beta.labels"] += b"5\n" * 1000
    with pytest.raises(SubmissionError, match=r"expected 80 lines .*, found 1080"):
        evaluate_submission(
            write_zip(tmp_path / "s.zip", members),
            challenge=custom_challenge(scans.gt_dir),
            chunk_size=32,
        )


def test_official_challenge_needs_ground_truth(tmp_path: Path) -> None:
    challenge = load_challenge("reduced-8", ground_truth_root=None)
    with pytest.raises(MissingGroundTruthError, match="expected ground truth for every scan"):
        evaluate_submission(tmp_path, challenge=challenge)


def test_invalid_ground_truth_is_not_the_submissions_fault(scans: Scans, tmp_path: Path) -> None:
    (scans.gt_dir / "beta.labels").write_bytes(b"1\n12\n" + b"1\n" * 78)
    with pytest.raises(DataFormatError, match=r"invalid ground truth: .*beta.labels: line 2"):
        evaluate_submission(
            scans.pred_folder(tmp_path / "s"), challenge=custom_challenge(scans.gt_dir)
        )


def test_ground_truth_disagreeing_with_the_protocol(tmp_path: Path) -> None:
    gt = tmp_path / "gt"
    gt.mkdir()
    spec = load_challenge("reduced-8", ground_truth_root=None)
    for scan in spec.scans:  # ground truth named as distributed: <scan>.labels
        (gt / f"{scan.name}.labels").write_bytes(b"1\n2\n")
    challenge = load_challenge("reduced-8", ground_truth_root=gt)
    submission = tmp_path / "sub"
    submission.mkdir()
    for name in challenge.submission_names:
        (submission / name).write_bytes(b"1\n2\n")
    with pytest.raises(DataFormatError, match=r"expected 10538633 lines for scan .*found 2"):
        evaluate_submission(submission, challenge=challenge)


def test_real_scan_against_sklearn(shared_data: Path, tmp_path: Path) -> None:
    """Oakland ground truth against a corrupted copy (20 % of labels replaced)."""
    gt_dir = shared_data / "oakland"
    rng = np.random.default_rng(11)
    members = {}
    truths, preds = [], []
    for path in sorted(gt_dir.glob("*.labels"))[:3]:
        truth = read_labels(path)
        pred = np.where(truth > 0, truth, 1)
        flip = rng.random(truth.size) < 0.2
        pred[flip] = rng.integers(1, 9, int(flip.sum()))
        members[path.name] = labels_bytes(pred)
        truths.append(truth)
        preds.append(pred)
    gt_subset = tmp_path / "gt"
    gt_subset.mkdir()
    for name in members:
        (gt_subset / name).symlink_to(gt_dir / name)
    result = evaluate_submission(
        write_zip(tmp_path / "s.zip", members), challenge=custom_challenge(gt_subset)
    )
    reference = _reference(np.concatenate(truths), np.concatenate(preds))
    np.testing.assert_array_equal(result.confusion, reference)
    # Oakland has no scanning artefacts: class 7 is only predicted (IoU 0, not absent)
    assert result.confusion[6].sum() == 0
    assert result.scores.iou[6] == 0.0


@pytest.mark.slow
def test_memory_stays_constant_on_a_large_scan(tmp_path: Path) -> None:
    """20 M lines (40 MB per file): the evaluator's own allocations stay a few chunks."""
    import tracemalloc

    from semantic3d.io import write_labels

    n, step = 20_000_000, 1 << 21
    rng = np.random.default_rng(0)
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    gt_dir.mkdir()
    pred_dir.mkdir()
    truth = [rng.integers(0, 9, min(step, n - s)) for s in range(0, n, step)]
    write_labels(gt_dir / "big.labels", truth)
    write_labels(pred_dir / "big.labels", (np.maximum(t, 1) for t in truth))
    del truth
    challenge = custom_challenge(gt_dir)
    evaluate_submission(pred_dir, challenge=challenge, chunk_size=1 << 16)  # compile, warm
    tracemalloc.start()
    result = evaluate_submission(pred_dir, challenge=challenge)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert result.scores.overall_accuracy == 1.0
    assert peak < 48 << 20  # two 4 MiB read buffers and a few 4 Mi-value chunks
