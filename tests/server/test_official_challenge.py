"""The benchmark's own reduced-8 challenge at full size (79 M points), served in-process."""

from __future__ import annotations

import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from semantic3d.evaluation import load_challenge
from semantic3d.io.labels import format_labels_bytes, write_labels
from semantic3d.server.services.challenges import install_challenge

from .conftest import build_harness, make_settings

pytestmark = pytest.mark.slow

BLOCK = 1 << 22


def _blocks(n: int, seed: int, *, prediction: bool) -> Iterator[np.ndarray]:
    truth_rng = np.random.default_rng(seed)
    noise_rng = np.random.default_rng(seed + 1000)
    for start in range(0, n, BLOCK):
        size = min(BLOCK, n - start)
        truth = np.repeat(truth_rng.integers(0, 9, size // 32 + 1).astype(np.uint8), 32)[:size]
        if not prediction:
            yield truth
            continue
        pred = np.maximum(truth, 1)
        flip = noise_rng.random(size) < 0.25
        pred[flip] = noise_rng.integers(1, 9, int(flip.sum()), dtype=np.uint8)
        yield pred


def test_reduced_8_with_its_official_names_and_sizes(tmp_path: Path) -> None:
    challenge = load_challenge("reduced-8", ground_truth_root=None)
    ground_truth = tmp_path / "reduced-8-gt"
    ground_truth.mkdir()
    preds = tmp_path / "reduced8.zip"
    with zipfile.ZipFile(preds, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for index, scan in enumerate(challenge.scans):
            assert scan.n_points is not None
            write_labels(
                ground_truth / f"{scan.name}.labels",
                _blocks(scan.n_points, index, prediction=False),
            )
            with archive.open(scan.submission_name, "w", force_zip64=True) as member:
                for block in _blocks(scan.n_points, index, prediction=True):
                    member.write(format_labels_bytes(block))

    settings = make_settings(tmp_path / "data", max_chunk_bytes=64 << 20)
    harness_iter = build_harness(settings, _toy_folder(tmp_path))
    harness = next(harness_iter)
    try:
        row = install_challenge(
            harness.state.factory,
            settings,
            "reduced-8",
            ground_truth,
            link=True,
            show_confusion=True,
        )
        assert row.kind == "reduced-8" and row.n_scans == 4
        assert row.n_points == sum(scan.n_points or 0 for scan in challenge.scans)
        token = harness.user_token("alice")
        upload_id = harness.upload(token, preds.read_bytes(), challenge="reduced-8", chunk=32 << 20)
        response = harness.finalize(token, upload_id, "full size")
        assert response.status_code == 201, response.text
        assert harness.work()
        headers = {"Authorization": f"Bearer {token}"}
        result = harness.client.get(
            f"/api/submissions/{response.json()['id']}", headers=headers
        ).json()
        assert result["status"] == "done", result
        confusion = np.array(result["scores"]["confusion"])
        assert confusion.sum() == result["scores"]["n_points"] > 60_000_000
        assert 0.5 < result["scores"]["mean_iou"] < 0.9
    finally:
        harness_iter.close()


def _toy_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "toy"
    folder.mkdir()
    write_labels(folder / "one.labels", [np.ones(10, dtype=np.uint8)])
    return folder
