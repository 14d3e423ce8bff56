"""The server's challenges: installing hidden ground truth, and the evaluation objects for it.

``semantic-8`` and ``reduced-8`` are the benchmark's own challenges (scan list and
submission names from :func:`semantic3d.evaluation.load_challenge`); any other name is
a custom challenge built from every ``*.labels`` file in its folder
(:func:`semantic3d.evaluation.custom_challenge`). Ground truth is copied (or linked)
into ``DATA_DIR/ground-truth/<name>/`` and is never served over HTTP.

The two benchmark challenges are listed from the start (a migration records them,
closed, without ground truth); installing their ground truth completes and opens them.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import threading
from dataclasses import replace
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.evaluation import Challenge, custom_challenge, load_challenge
from semantic3d.evaluation.submission import count_ground_truth_lines
from semantic3d.server.db import write_transaction
from semantic3d.server.errors import InvalidInputError, NotFoundError
from semantic3d.server.models import ChallengeRecord
from semantic3d.server.settings import Settings

logger = logging.getLogger(__name__)

BENCHMARK_CHALLENGES = ("semantic-8", "reduced-8")
CHALLENGE_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{1,63}$")

CONFUSION_MIN_SCANS = 10
"""Fewest scans for which participants see confusion matrices (unless overridden per challenge).

A participant who predicts one class per scan reads each scan's ground-truth class counts
off the matrix's columns; with at least this many scans (more than the 8 classes) no single
submission isolates every scan, and the submission cooldown slows the rest.
"""

NOT_INSTALLED = "not open yet: ground truth not installed"


def accepts_submissions(row: ChallengeRecord) -> bool:
    """True when ``row`` takes new submissions: ground truth installed and open."""
    return row.ground_truth_installed and row.is_open


def submission_status(row: ChallengeRecord) -> str:
    """``"open"``, ``"closed"`` or :data:`NOT_INSTALLED`, as the pages and the API say it."""
    if not row.ground_truth_installed:
        return NOT_INSTALLED
    return "open" if row.is_open else "closed"


def install_hint(name: str) -> str:
    """The command an administrator runs to install the ground truth of ``name``."""
    return f"semantic3d admin add-challenge {name} --ground-truth DIR"


def shows_confusion(row: ChallengeRecord) -> bool:
    """Whether participants (owners included) see confusion matrices of this challenge.

    The challenge's ``show_confusion`` when set, else at least :data:`CONFUSION_MIN_SCANS`
    scans. Mean IoU, overall accuracy and per-class IoU are always shown.
    """
    if row.show_confusion is not None:
        return row.show_confusion
    return row.n_scans >= CONFUSION_MIN_SCANS


def ground_truth_folder(settings: Settings, name: str) -> Path:
    """Where the hidden ground truth of challenge ``name`` lives."""
    return settings.ground_truth_dir / name


def build_challenge(settings: Settings, row: ChallengeRecord) -> Challenge:
    """The evaluation's :class:`~semantic3d.evaluation.Challenge` for a stored challenge.

    Point counts recorded at installation fill the scans that lack one (custom
    challenges), so validating a submission never re-reads the ground truth.
    """
    root = ground_truth_folder(settings, row.name)
    if row.kind in BENCHMARK_CHALLENGES:
        built = load_challenge(row.kind, ground_truth_root=root)
    else:
        built = custom_challenge(root, name=row.name)
    counts: dict[str, int] = json.loads(row.scan_points_json or "{}")
    scans = tuple(
        replace(scan, n_points=counts.get(scan.submission_name)) if scan.n_points is None else scan
        for scan in built.scans
    )
    return replace(built, scans=scans)


class ChallengeCache:
    """Built challenges by name, so each request does not rescan the ground-truth folder."""

    def __init__(self, settings: Settings) -> None:
        self._settings = settings
        self._lock = threading.Lock()
        self._built: dict[tuple[str, int], Challenge] = {}

    def get(self, row: ChallengeRecord) -> Challenge:
        """The challenge for ``row`` (rebuilt when the row was re-installed)."""
        key = (row.name, row.id)
        with self._lock:
            cached = self._built.get(key)
        if cached is None:
            cached = build_challenge(self._settings, row)
            with self._lock:
                self._built[key] = cached
        return cached


def install_challenge(
    factory: sessionmaker[Session],
    settings: Settings,
    name: str,
    ground_truth: Path,
    *,
    link: bool = False,
    title: str | None = None,
    description: str = "",
    show_confusion: bool | None = None,
) -> ChallengeRecord:
    """Install a challenge from a folder of ground-truth ``.labels`` files.

    ``name`` ``semantic-8``/``reduced-8`` installs the benchmark's challenge (the folder
    must hold its test scans' ground truth); any other name a custom challenge. Files are
    hard-linked or copied under the data dir (``link=True``: symbolic links to the
    originals, which must then stay in place). The challenge is built once to check the
    files before it is recorded; on error nothing is left behind. A benchmark challenge
    listed without ground truth is completed and opened. ``show_confusion`` overrides the
    rule of :func:`shows_confusion` (``None``: follow it).
    """
    if not CHALLENGE_NAME.match(name):
        raise InvalidInputError(
            f"challenge name {name!r}: expected 2-64 characters a-z, 0-9, '-', '_'"
        )
    source = ground_truth.expanduser().resolve()
    if not source.is_dir():
        raise InvalidInputError(f"{ground_truth}: expected a folder of .labels files")
    files = sorted(source.glob("*.labels"))
    if not files:
        raise InvalidInputError(f"{ground_truth}: expected .labels files, found none")
    settings.prepare_data_dir()
    with factory() as session:
        listed = session.scalars(
            select(ChallengeRecord).where(ChallengeRecord.name == name)
        ).one_or_none()
    if listed is not None and listed.ground_truth_installed:
        raise InvalidInputError(f"challenge {name!r} is already installed")
    target = ground_truth_folder(settings, name)
    if target.exists():
        raise InvalidInputError(f"challenge {name!r} is already installed ({target})")
    staging = target.with_name(f".{name}.installing")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(mode=0o700)
    try:
        for path in files:
            _place(path, staging / path.name, link=link)
        staging.rename(target)
        row = ChallengeRecord(
            name=name,
            kind=name if name in BENCHMARK_CHALLENGES else "custom",
            title=title or (listed.title if listed is not None else name),
            description=description or (listed.description if listed is not None else ""),
        )
        row.scan_points_json = "{}"
        built = build_challenge(settings, row)
        # Count (and check) every ground-truth file once, now, instead of per submission.
        counts = {scan.submission_name: count_ground_truth_lines(scan) for scan in built.scans}
        row.scan_points_json = json.dumps(counts, sort_keys=True)
        row.protocol_version = str(built.protocol_version)
        row.n_scans = len(built.scans)
        row.n_points = sum(counts.values())
        row.is_open = True
        row.ground_truth_installed = True
        row.show_confusion = show_confusion
        with write_transaction(factory) as session:
            if listed is None:
                session.add(row)
            else:
                _complete_listed(session, listed.id, row)
    except IntegrityError:
        shutil.rmtree(target, ignore_errors=True)
        raise InvalidInputError(f"challenge {name!r} already exists") from None
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(target, ignore_errors=True)
        raise
    logger.info("installed challenge %s: %d scans", name, row.n_scans)
    return row


def _complete_listed(session: Session, challenge_id: int, installed: ChallengeRecord) -> None:
    """Fill the listed (not yet installed) challenge ``challenge_id`` from ``installed``."""
    row = session.get(ChallengeRecord, challenge_id)
    if row is None or row.ground_truth_installed:
        raise InvalidInputError(f"challenge {installed.name!r} already exists")
    for column in (
        "title",
        "description",
        "protocol_version",
        "n_scans",
        "n_points",
        "scan_points_json",
        "is_open",
        "ground_truth_installed",
        "show_confusion",
    ):
        setattr(row, column, getattr(installed, column))
    installed.id = row.id


def _place(source: Path, target: Path, *, link: bool) -> None:
    if link:
        target.symlink_to(source)
        return
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)


def list_challenges(factory: sessionmaker[Session]) -> list[ChallengeRecord]:
    """Every challenge: the benchmark's own first (semantic-8, reduced-8), then by name."""
    with factory() as session:
        rows = list(session.scalars(select(ChallengeRecord).order_by(ChallengeRecord.name)))
    order = {name: position for position, name in enumerate(BENCHMARK_CHALLENGES)}
    return sorted(rows, key=lambda row: (order.get(row.name, len(order)), row.name))


def get_challenge(session: Session, name: str) -> ChallengeRecord:
    """The challenge called ``name`` or :class:`NotFoundError`."""
    row = session.scalars(select(ChallengeRecord).where(ChallengeRecord.name == name)).one_or_none()
    if row is None:
        raise NotFoundError(f"no challenge named {name!r}")
    return row


def set_challenge_open(factory: sessionmaker[Session], name: str, *, is_open: bool) -> None:
    """Open or close a challenge to new submissions (its leaderboard stays visible).

    A challenge whose ground truth is not installed cannot be opened.
    """
    with write_transaction(factory) as session:
        row = get_challenge(session, name)
        if is_open and not row.ground_truth_installed:
            raise InvalidInputError(
                f"challenge {name!r} is {NOT_INSTALLED}: install it first with "
                f"`{install_hint(name)}`"
            )
        row.is_open = is_open


def set_show_confusion(factory: sessionmaker[Session], name: str, *, show: bool | None) -> None:
    """Show (``True``) or hide (``False``) confusion matrices, or follow the rule (``None``)."""
    with write_transaction(factory) as session:
        get_challenge(session, name).show_confusion = show
