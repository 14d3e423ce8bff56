"""Results on a cluster of worker processes equal the single-process path's, byte for byte."""

from __future__ import annotations

import filecmp
import shutil
from pathlib import Path

import numpy as np
import pytest

from semantic3d.baselines.common.submission import ScanToLabel
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.baselines.covariance.predict import predict_scan, predict_scans
from semantic3d.core.errors import ConfigError, SubmissionError
from semantic3d.evaluation.agreement import compute_label_agreement_files
from semantic3d.evaluation.challenge import custom_challenge
from semantic3d.evaluation.evaluate import evaluate_submission
from semantic3d.evaluation.report import write_json
from semantic3d.scale.cluster import ClusterError, ClusterSpec, DaskCluster, connect
from semantic3d.scale.evaluation import (
    compute_label_agreement_on_cluster,
    evaluate_submission_on_cluster,
)
from semantic3d.scale.predict import predict_scan_on_cluster, predict_scans_on_cluster


def test_predict_one_scan_identical(
    cluster: DaskCluster, model: CovarianceModel, scan_dir: Path, tmp_path: Path
) -> None:
    single = predict_scan(model, scan_dir / "test.txt", out_path=tmp_path / "single.labels")
    seen: list[tuple[int, int]] = []
    distributed = predict_scan_on_cluster(
        model,
        scan_dir / "test.txt",
        cluster=cluster,
        out_path=tmp_path / "cluster.labels",
        progress=lambda done, total: seen.append((done, total)),
    )
    assert distributed.tiled and distributed.n_points == single.n_points
    assert seen[-1] == (single.n_points, single.n_points)
    assert filecmp.cmp(single.labels_path, distributed.labels_path, shallow=False)


def test_predict_many_scans_identical(
    cluster: DaskCluster, model: CovarianceModel, scan_dir: Path, tmp_path: Path
) -> None:
    scans = [
        ScanToLabel(name, scan_dir / f"{name}.txt", f"{name}.labels") for name in ("test", "other")
    ]
    predict_scans(model, scans, tmp_path / "single")
    predict_scans_on_cluster(model, scans, tmp_path / "cluster", cluster=cluster)
    for scan in scans:
        assert filecmp.cmp(
            tmp_path / "single" / scan.output_name,
            tmp_path / "cluster" / scan.output_name,
            shallow=False,
        )


def _submission(folder: Path, truth: Path, *, corrupt: str | None = None) -> Path:
    """A prediction folder: the ground truth with every tenth label changed."""
    folder.mkdir()
    for path in sorted(truth.glob("*.labels")):
        values = np.loadtxt(path, dtype=np.int64)
        values[::10] = (values[::10] % 8) + 1
        lines = "\n".join(map(str, values)) + "\n"
        if path.stem == corrupt:
            lines = lines.replace("\n", "\n9\n", 1)
        (folder / path.name).write_text(lines)
    return folder


def test_evaluate_identical(cluster: DaskCluster, scan_dir: Path, tmp_path: Path) -> None:
    truth = tmp_path / "truth"
    truth.mkdir()
    for name in ("test", "other", "train"):
        shutil.copy(scan_dir / f"{name}.labels", truth)
    challenge = custom_challenge(truth)
    submission = _submission(tmp_path / "pred", truth)
    single = evaluate_submission(submission, challenge=challenge)
    distributed = evaluate_submission_on_cluster(submission, challenge=challenge, cluster=cluster)
    write_json(tmp_path / "single.json", single)
    write_json(tmp_path / "cluster.json", distributed)
    assert len(distributed.per_scan) == 3 and distributed.n_points > 0
    assert (tmp_path / "single.json").read_bytes() == (tmp_path / "cluster.json").read_bytes()


def test_evaluate_problems_identical(cluster: DaskCluster, scan_dir: Path, tmp_path: Path) -> None:
    truth = tmp_path / "truth"
    truth.mkdir()
    for name in ("test", "other"):
        shutil.copy(scan_dir / f"{name}.labels", truth)
    challenge = custom_challenge(truth)
    submission = _submission(tmp_path / "pred", truth, corrupt="other")
    with pytest.raises(SubmissionError, match=r"other\.labels") as single:
        evaluate_submission(submission, challenge=challenge)
    with pytest.raises(SubmissionError, match=r"other\.labels") as distributed:
        evaluate_submission_on_cluster(submission, challenge=challenge, cluster=cluster)
    assert distributed.value.problems == single.value.problems


def test_agreement_identical(cluster: DaskCluster, scan_dir: Path, tmp_path: Path) -> None:
    pair = [
        scan_dir / "test.txt",
        scan_dir / "test.labels",
        scan_dir / "other.txt",
        scan_dir / "other.labels",
    ]
    single = compute_label_agreement_files(*pair, max_distance_m=0.15, tile_size_m=2.0)
    tiles: list[int] = []
    distributed = compute_label_agreement_on_cluster(
        *pair,
        cluster=cluster,
        max_distance_m=0.15,
        tile_size_m=2.0,
        spill_directory=tmp_path,
        progress=lambda done, total: tiles.append(total),
    )
    assert tiles[-1] > 20  # many tile tasks
    assert not any(tmp_path.iterdir())  # the stores are removed
    for one, other in zip(single.directions, distributed.directions, strict=True):
        assert other.n_matched > 0
        np.testing.assert_array_equal(other.confusion, one.confusion)
        assert (other.n_points, other.n_matched) == (one.n_points, one.n_matched)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({}, "found neither"),
        ({"scheduler": "tcp://127.0.0.1:1", "n_workers": 1}, "found both"),
        ({"n_workers": 0}, "expected at least 1, found 0"),
        ({"scheduler": "127.0.0.1:8786"}, "expected an address like tcp://HOST:8786"),
    ],
)
def test_cluster_spec_rejects_bad_settings(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        ClusterSpec(**kwargs)  # type: ignore[arg-type]


def test_unreachable_scheduler_is_named() -> None:
    with pytest.raises(ClusterError, match=r"tcp://127\.0\.0\.1:9: expected a Dask scheduler"):
        connect(ClusterSpec(scheduler="tcp://127.0.0.1:9", timeout_s=0.3))
