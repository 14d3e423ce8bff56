"""The semantic3D.net benchmark: protocol, challenges, submission validation, evaluation.

Also the paper's two analysis tools: points per class per split (:mod:`.stats`) and the
label agreement of overlapping scans (:mod:`.agreement`). Reports live in :mod:`.report`.
The convention (rows ground truth, ground truth 0 dropped, absent classes NaN and left
out of the mean) is written once in ``docs/evaluation.md`` and ``protocol_v1.toml``.

>>> from semantic3d.evaluation import load_challenge
>>> load_challenge("reduced-8", ground_truth_root=None).submission_names[0]
'marketsquarefeldkirch4-reduced.labels'
"""

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
