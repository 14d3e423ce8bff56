"""Evaluation and label agreement with the scans, or the tiles, scored on a Dask cluster.

Thin wrappers: :func:`~semantic3d.evaluation.evaluate.evaluate_submission` with one task
per scan (:func:`~semantic3d.evaluation.evaluate.evaluate_submitted_scan`) and
:func:`~semantic3d.evaluation.agreement.compute_label_agreement` with one task per tile
(:func:`~semantic3d.evaluation.agreement.match_store_tile`). The per-scan and per-tile
confusion matrices come back in input order and are merged with
:meth:`~semantic3d.metrics.confusion.ConfusionMatrix.merge` exactly as the
single-process path merges them, so the results are identical.
"""

from __future__ import annotations

from pathlib import Path

from semantic3d.evaluation.agreement import (
    DEFAULT_MAX_DISTANCE_M,
    DEFAULT_TILE_SIZE_M,
    AgreementProgress,
    AgreementResult,
    compute_label_agreement_files,
)
from semantic3d.evaluation.challenge import Challenge
from semantic3d.evaluation.contents import SubmissionLimits
from semantic3d.evaluation.evaluate import DEFAULT_EVALUATION_CHUNK, evaluate_submission
from semantic3d.evaluation.result import EvaluationResult, MethodInfo
from semantic3d.evaluation.submission import ProgressCallback
from semantic3d.scale.cluster import DaskCluster

__all__ = ["compute_label_agreement_on_cluster", "evaluate_submission_on_cluster"]


def evaluate_submission_on_cluster(
    submission: Path,
    *,
    challenge: Challenge,
    cluster: DaskCluster,
    method: MethodInfo | None = None,
    limits: SubmissionLimits = SubmissionLimits(),
    progress: ProgressCallback | None = None,
    chunk_size: int = DEFAULT_EVALUATION_CHUNK,
) -> EvaluationResult:
    """:func:`~semantic3d.evaluation.evaluate.evaluate_submission`, one task per scan.

    The submission and the ground truth must be visible to the workers at the same paths.
    """
    return evaluate_submission(
        submission,
        challenge=challenge,
        method=method,
        limits=limits,
        progress=progress,
        chunk_size=chunk_size,
        map_scans=cluster.map,
    )


def compute_label_agreement_on_cluster(
    a_points: Path,
    a_labels: Path,
    b_points: Path,
    b_labels: Path,
    *,
    cluster: DaskCluster,
    max_distance_m: float = DEFAULT_MAX_DISTANCE_M,
    tile_size_m: float = DEFAULT_TILE_SIZE_M,
    buffer_points: int = 1 << 24,
    spill_directory: Path | None = None,
    progress: AgreementProgress | None = None,
    exclude_before_matching: bool = False,
) -> AgreementResult:
    """:func:`~semantic3d.evaluation.agreement.compute_label_agreement_files`, one task per tile.

    The scans are read here and binned into two tile stores under ``spill_directory``
    (the system's temporary folder by default), which the workers must see.
    """
    return compute_label_agreement_files(
        a_points,
        a_labels,
        b_points,
        b_labels,
        max_distance_m=max_distance_m,
        tile_size_m=tile_size_m,
        buffer_points=buffer_points,
        spill_directory=spill_directory,
        progress=progress,
        exclude_before_matching=exclude_before_matching,
        map_tiles=cluster.map,
    )
