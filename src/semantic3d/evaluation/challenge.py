"""Challenges: which scans a submission must label, under which file names.

``semantic-8`` and ``reduced-8`` come from the protocol file; any folder of ground-truth
``.labels`` files defines a custom challenge (:func:`custom_challenge`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from semantic3d.core.errors import Semantic3DError
from semantic3d.evaluation.protocol import CURRENT_PROTOCOL_VERSION, load_protocol

OFFICIAL_CHALLENGES = ("semantic-8", "reduced-8")
"""Names accepted by :func:`load_challenge`."""

LABELS_SUFFIX = ".labels"


class MissingGroundTruthError(Semantic3DError, FileNotFoundError):
    """Ground-truth label files needed to evaluate a challenge are not where expected."""


@dataclass(frozen=True, slots=True)
class ChallengeScan:
    """One scan of a challenge.

    Attributes:
        name: the scan's name (official: the archive name without ``.7z``).
        submission_name: the file name a submission must use for this scan.
        ground_truth: the scan's ground-truth ``.labels`` file, when available.
        n_points: the number of points (= label lines), when known.
    """

    name: str
    submission_name: str
    ground_truth: Path | None
    n_points: int | None


@dataclass(frozen=True, slots=True)
class Challenge:
    """A set of scans to label; the unit a submission is validated and evaluated against."""

    name: str
    protocol_version: str
    scans: tuple[ChallengeScan, ...]

    @property
    def submission_names(self) -> tuple[str, ...]:
        """The file names a submission must contain, in protocol order."""
        return tuple(scan.submission_name for scan in self.scans)

    @property
    def has_ground_truth(self) -> bool:
        """True when every scan has a ground-truth file."""
        return all(scan.ground_truth is not None for scan in self.scans)

    def require_ground_truth(self) -> None:
        """Raise :class:`MissingGroundTruthError` naming every scan without ground truth."""
        missing = [scan.name for scan in self.scans if scan.ground_truth is None]
        if missing:
            raise MissingGroundTruthError(
                f"challenge {self.name!r}: expected ground truth for every scan, "
                f"found none for {', '.join(missing)}"
            )


def _find_ground_truth(root: Path, scan_name: str, submission_name: str) -> Path | None:
    for candidate in (root / f"{scan_name}{LABELS_SUFFIX}", root / submission_name):
        if candidate.is_file():
            return candidate
    return None


def load_challenge(name: str, *, ground_truth_root: Path | None) -> Challenge:
    """An official challenge (``semantic-8`` or ``reduced-8``).

    Ground truth of a scan is looked up in ``ground_truth_root`` as ``<scan name>.labels``
    (as distributed), then as its submission file name. With ``ground_truth_root`` None,
    the challenge can validate submissions (line counts come from the protocol) but not
    evaluate them.

    Raises:
        ValueError: ``name`` is not an official challenge.
        MissingGroundTruthError: ``ground_truth_root`` is given but lacks some scans.
    """
    protocol = load_protocol(CURRENT_PROTOCOL_VERSION)
    spec = protocol.challenges.get(name)
    if spec is None:
        known = ", ".join(protocol.challenges)
        raise ValueError(f"unknown challenge {name!r}: expected one of {known} (or custom)")
    if ground_truth_root is not None and not ground_truth_root.is_dir():
        raise MissingGroundTruthError(
            f"{ground_truth_root}: expected a folder of ground-truth .labels files, found none"
        )
    scans = tuple(
        ChallengeScan(
            name=scan.name,
            submission_name=scan.submission_name,
            ground_truth=None
            if ground_truth_root is None
            else _find_ground_truth(ground_truth_root, scan.name, scan.submission_name),
            n_points=scan.n_points,
        )
        for scan in spec.scans
    )
    challenge = Challenge(name=name, protocol_version=protocol.version, scans=scans)
    if ground_truth_root is not None:
        missing = [
            f"{scan.name}{LABELS_SUFFIX} (or {scan.submission_name})"
            for scan in scans
            if scan.ground_truth is None
        ]
        if missing:
            raise MissingGroundTruthError(
                f"{ground_truth_root}: expected ground truth of every {name} scan, "
                f"missing {len(missing)}: {', '.join(missing)}"
            )
    return challenge


def custom_challenge(ground_truth_root: Path, *, name: str | None = None) -> Challenge:
    """A challenge made of every ``*.labels`` file in ``ground_truth_root`` (not recursive).

    Each file is a scan named after its stem; a submission must contain a file of the same
    name with as many lines. Hidden files (``._x.labels`` left by macOS, a writer's
    ``.x.<tag>.partial.labels``) are not scans.
    """
    if not ground_truth_root.is_dir():
        raise MissingGroundTruthError(
            f"{ground_truth_root}: expected a folder of ground-truth .labels files, found none"
        )
    files = sorted(
        path
        for path in ground_truth_root.iterdir()
        if path.suffix == LABELS_SUFFIX and not path.name.startswith(".") and path.is_file()
    )
    if not files:
        raise MissingGroundTruthError(
            f"{ground_truth_root}: expected at least one *.labels file, found none"
        )
    scans = tuple(
        ChallengeScan(name=path.stem, submission_name=path.name, ground_truth=path, n_points=None)
        for path in files
    )
    return Challenge(
        name=name or f"custom:{ground_truth_root.name}",
        protocol_version=CURRENT_PROTOCOL_VERSION,
        scans=scans,
    )
