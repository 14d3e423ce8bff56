"""The semantic3D.net benchmark: protocol, challenges, submission validation, evaluation.

Also the paper's two analysis tools: points per class per split (:mod:`.stats`) and the
label agreement of overlapping scans (:mod:`.agreement`). Reports live in :mod:`.report`.
The convention (rows ground truth, ground truth 0 dropped, absent classes NaN and left
out of the mean) is written once in ``docs/evaluation.md`` and ``protocol_v1.toml``.

>>> from semantic3d.evaluation import load_challenge
>>> load_challenge("reduced-8", ground_truth_root=None).submission_names[0]
'marketsquarefeldkirch4-reduced.labels'
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.evaluation.agreement import (
        AgreementDirection,
        AgreementResult,
        compute_label_agreement,
        compute_label_agreement_files,
    )
    from semantic3d.evaluation.challenge import (
        OFFICIAL_CHALLENGES,
        Challenge,
        ChallengeScan,
        MissingGroundTruthError,
        custom_challenge,
        load_challenge,
    )
    from semantic3d.evaluation.evaluate import evaluate_submission
    from semantic3d.evaluation.protocol import CURRENT_PROTOCOL_VERSION, Protocol, load_protocol
    from semantic3d.evaluation.result import EvaluationResult, MethodInfo, ScanResult
    from semantic3d.evaluation.stats import ClassStatistics, compute_class_statistics
    from semantic3d.evaluation.submission import SubmissionLimits, validate_submission

__all__ = [
    "CURRENT_PROTOCOL_VERSION",
    "OFFICIAL_CHALLENGES",
    "AgreementDirection",
    "AgreementResult",
    "Challenge",
    "ChallengeScan",
    "ClassStatistics",
    "EvaluationResult",
    "MethodInfo",
    "MissingGroundTruthError",
    "Protocol",
    "ScanResult",
    "SubmissionLimits",
    "compute_class_statistics",
    "compute_label_agreement",
    "compute_label_agreement_files",
    "custom_challenge",
    "evaluate_submission",
    "load_challenge",
    "load_protocol",
    "validate_submission",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "CURRENT_PROTOCOL_VERSION": "semantic3d.evaluation.protocol",
        "OFFICIAL_CHALLENGES": "semantic3d.evaluation.challenge",
        "AgreementDirection": "semantic3d.evaluation.agreement",
        "AgreementResult": "semantic3d.evaluation.agreement",
        "Challenge": "semantic3d.evaluation.challenge",
        "ChallengeScan": "semantic3d.evaluation.challenge",
        "ClassStatistics": "semantic3d.evaluation.stats",
        "EvaluationResult": "semantic3d.evaluation.result",
        "MethodInfo": "semantic3d.evaluation.result",
        "MissingGroundTruthError": "semantic3d.evaluation.challenge",
        "Protocol": "semantic3d.evaluation.protocol",
        "ScanResult": "semantic3d.evaluation.result",
        "SubmissionLimits": "semantic3d.evaluation.submission",
        "compute_class_statistics": "semantic3d.evaluation.stats",
        "compute_label_agreement": "semantic3d.evaluation.agreement",
        "compute_label_agreement_files": "semantic3d.evaluation.agreement",
        "custom_challenge": "semantic3d.evaluation.challenge",
        "evaluate_submission": "semantic3d.evaluation.evaluate",
        "load_challenge": "semantic3d.evaluation.challenge",
        "load_protocol": "semantic3d.evaluation.protocol",
        "validate_submission": "semantic3d.evaluation.submission",
    },
)
