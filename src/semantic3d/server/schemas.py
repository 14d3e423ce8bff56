"""The JSON the API answers with (and the bodies it takes), as pydantic models.

The routers declare these as ``response_model`` (so ``/api/openapi.json`` documents every
response) and :class:`~semantic3d.server.client.BenchmarkClient` parses its answers into
them: server and client share one description of the API. Scores are fractions (0..1),
``None`` where unknown or absent; times are ISO 8601 with their UTC offset. Needs only
pydantic (no web framework), so the client can use it.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, PlainSerializer

from semantic3d.evaluation import MethodInfo

UtcTime = Annotated[
    datetime, PlainSerializer(lambda value: value.isoformat(), return_type=str, when_used="json")
]
"""An aware UTC time, written as ``datetime.isoformat()`` does (``…+00:00``)."""

MAX_RUNTIME_S = 1e7
"""Largest run time a method card may state (115 days); also refuses ``1e308``."""


class ApiModel(BaseModel):
    """Base of the API's models: unknown fields are ignored (newer servers may add some)."""

    model_config = ConfigDict(extra="ignore")


class ErrorBody(ApiModel):
    """Every error: the message, plus what applies to it."""

    error: str
    problems: list[str] | None = Field(default=None, description="invalid submission (422)")
    offset: int | None = Field(default=None, description="where to resume an upload (409)")
    retry_after_s: int | None = Field(default=None, description="when to try again (429, 503)")


class Health(ApiModel):
    """Liveness."""

    status: str
    version: str


class Account(ApiModel):
    """The account a token (or session) belongs to."""

    username: str
    is_admin: bool


class ClassInfo(ApiModel):
    """One of the benchmark's classes: label value, name and colour (``#rrggbb``)."""

    value: int
    name: str
    colour: str


class ChallengeInfo(ApiModel):
    """A challenge (never where its ground truth lives)."""

    name: str
    title: str
    description: str
    kind: str = Field(description='"semantic-8", "reduced-8" or "custom"')
    protocol_version: str
    n_scans: int
    n_points: int | None
    open: bool
    ground_truth_installed: bool
    accepts_submissions: bool
    status: str = Field(description='"open", "closed" or why not open yet')
    shows_confusion: bool = Field(description="whether participants see confusion matrices")
    classes: list[ClassInfo]


class ChallengeList(ApiModel):
    """Every challenge of the server."""

    challenges: list[ChallengeInfo]


class ReferenceSource(ApiModel):
    """A publication reference values were read from."""

    citation: str
    url: str
    label: str
    year: int | None = None


class LeaderboardRow(ApiModel):
    """A participant's published submission, or a reference result (no rank, no date).

    ``tag`` is ``"verified"`` (a submission this server evaluated), ``"paper-baseline"``
    (a baseline of the semantic3D.net paper) or ``"published"`` (published elsewhere,
    not verified here); ``position`` is the row's place on the board's page (1 first).
    """

    rank: int | None
    reference: bool
    submission_id: int | None
    method: str
    submitted_by: str
    mean_iou: float | None
    overall_accuracy: float | None
    iou: dict[str, float | None] = Field(description="label value -> IoU")
    runtime_s: float | None = Field(description="the run time T the authors report")
    hardware: str | None
    submitted_at: UtcTime | None
    paper_url: str
    code_url: str
    tag: str = Field(default="verified", description='"verified", "paper-baseline" or "published"')
    position: int | None = Field(default=None, description="place on the board page, 1 first")
    method_page: str = Field(default="", description="path of the row's method page")
    source: ReferenceSource | None = Field(
        default=None, description="where a reference row's values were read"
    )
    table: str = Field(default="", description="where in the source the row is printed")
    iou_notes: dict[str, str] = Field(
        default_factory=dict, description="label value -> the source's footnote on that cell"
    )
    description: str = Field(default="", description="the method, in Markdown")
    note: str = ""


class Leaderboard(ApiModel):
    """A challenge's public board: ranked ``entries`` and, apart, unranked ``references``.

    ``reference_source`` is the semantic3D.net paper (the benchmark's own publication);
    each reference row names its own ``source``.
    """

    challenge: ChallengeInfo
    entries: list[LeaderboardRow]
    references: list[LeaderboardRow]
    reference_source: ReferenceSource | None


class UploadInfo(ApiModel):
    """An unfinished upload: what a client needs to continue it."""

    id: str
    challenge: str
    size_bytes: int
    received_bytes: int
    filename: str
    sha256: str | None
    complete: bool
    created_at: UtcTime | None
    expires_at: UtcTime | None


class OpenedUpload(UploadInfo):
    """An upload just opened (or resumed), with the largest chunk the server takes."""

    max_chunk_bytes: int


class UploadList(ApiModel):
    """The caller's unfinished uploads, oldest first."""

    uploads: list[UploadInfo]
    max_open_uploads: int


class ChunkReceived(ApiModel):
    """Where an upload stands after a chunk."""

    id: str
    received_bytes: int
    size_bytes: int
    complete: bool


class MethodCard(ApiModel):
    """The method description shown on the leaderboard."""

    name: str
    description: str = ""
    paper_url: str = ""
    code_url: str = ""
    runtime_s: float | None = None
    hardware: str | None = None

    @classmethod
    def from_method(cls, method: MethodInfo) -> MethodCard:
        """The card of ``method``."""
        return cls.model_validate(method.to_dict())

    def to_method(self) -> MethodInfo:
        """The card as the evaluation's :class:`~semantic3d.evaluation.MethodInfo`."""
        return MethodInfo.from_dict(self.model_dump())


class MethodCardIn(MethodCard):
    """A method card sent with a submission (limits checked)."""

    name: str = Field(min_length=1, max_length=200)
    description: str = Field(default="", max_length=20_000)
    paper_url: str = Field(default="", max_length=500)
    code_url: str = Field(default="", max_length=500)
    runtime_s: float | None = Field(default=None, ge=0, le=MAX_RUNTIME_S, allow_inf_nan=False)
    hardware: str | None = Field(default=None, max_length=200)


class UploadRequest(ApiModel):
    """Open an upload: what is coming and how big it is."""

    challenge: str = Field(max_length=64)
    size_bytes: int = Field(gt=0)
    filename: str = Field(default="submission.zip", max_length=1000)
    sha256: str | None = Field(default=None, description="hex digest; makes create resumable")


class FinalizeRequest(ApiModel):
    """Finish an upload: the method card of the submission."""

    method: MethodCardIn


class PublishRequest(ApiModel):
    """Show (``true``) or hide (``false``) an evaluated submission on its leaderboard."""

    published: bool


class Progress(ApiModel):
    """Points evaluated so far of the total."""

    done: int
    total: int


class SubmissionScores(ApiModel):
    """Overall scores of an evaluated submission (per-scan scores are never shown)."""

    mean_iou: float | None
    overall_accuracy: float | None
    iou: list[float | None] = Field(description="per class, in label-value order")
    n_points: int
    confusion: list[list[int]] | None = Field(
        description="rows ground truth; null where the challenge's policy hides it"
    )


class SubmissionInfo(ApiModel):
    """A submission: status, progress, method card, scores once evaluated.

    ``filename``, ``size_bytes``, ``sha256``, ``error`` and ``attempts`` are sent to the
    submission's owner only (absent otherwise).
    """

    id: int
    challenge: str
    status: str = Field(description='"queued", "running", "done" or "failed"')
    progress: Progress
    created_at: UtcTime
    finished_at: UtcTime | None
    published: bool
    method: MethodCard
    scores: SubmissionScores | None
    filename: str | None = None
    size_bytes: int | None = None
    sha256: str | None = None
    error: str | None = None
    attempts: int | None = None

    @property
    def finished(self) -> bool:
        """Whether the evaluation is over (done or failed)."""
        return self.status in ("done", "failed")


class SubmissionList(ApiModel):
    """The caller's submissions, newest first."""

    submissions: list[SubmissionInfo]


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` documenting ``statuses`` as :class:`ErrorBody`."""
    return {status: {"model": ErrorBody} for status in statuses}
