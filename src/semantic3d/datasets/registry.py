"""The semantic3D.net benchmark's scans: splits, archive addresses, file names, submission names.

Thirty static terrestrial scans: 15 training scans (points and ground truth), 15 semantic-8
test scans, plus the 4 reduced-8 test scans (sub-sampled copies of four semantic-8 scans,
with their own files). Every fact here is cited in ``docs/datasets.md``.

Traps this table encodes so that no caller has to:

- the neugasse training archive unpacks to ``station1_xyz_intensity_rgb.txt``; the local
  file (and its ``.labels`` file) is ``neugasse_station1_xyz_intensity_rgb.*``;
- test data says ``marketplacefeldkirch`` but submission files say ``marketsquarefeldkirch``;
- the training labels come in one shared archive, ``sem8_labels_training.7z``;
- reduced-8 archives are ``<stem>.txt.7z`` (not ``<stem>.7z``) and their stems use mixed case
  and ``rgb_intensity-reduced``.

>>> scan("neugasse_station1").points.member
'station1_xyz_intensity_rgb.txt'
>>> submission_name("marketplacefeldkirch_station4", Split.REDUCED_8)
'marketsquarefeldkirch4-reduced.labels'
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from semantic3d.core.errors import Semantic3DError

__all__ = [
    "DEFAULT_BASE_URL",
    "LABELS_ARCHIVE",
    "REFERENCE_FOLDS",
    "REFERENCE_VALIDATION_FOLD",
    "ArchiveFile",
    "ScanInfo",
    "Split",
    "UnknownScanError",
    "reference_split",
    "scan",
    "scans",
    "submission_name",
]

#: Where the benchmark hosted its archives (the server has been unreachable since 2024;
#: pass ``base_url`` to the downloader to use a mirror).
DEFAULT_BASE_URL = "http://semantic3d.net/data/"

#: The one archive holding the ground truth of all 15 training scans.
LABELS_ARCHIVE = "sem8_labels_training.7z"


class Split(StrEnum):
    """A group of scans: the training scans or the scans of one test challenge."""

    TRAIN = "train"
    SEMANTIC_8 = "semantic-8"
    REDUCED_8 = "reduced-8"

    @property
    def is_challenge(self) -> bool:
        """Whether this split is a test challenge (its scans have submission names)."""
        return self is not Split.TRAIN


class UnknownScanError(Semantic3DError, LookupError):
    """A scan name, split or challenge that the registry does not know."""


@dataclass(frozen=True, slots=True)
class ArchiveFile:
    """One file of the benchmark: where it is packed and what it is called once unpacked.

    ``archive`` is the archive's address relative to the data root (``DEFAULT_BASE_URL`` or
    a mirror), ``member`` the file's name inside the archive, ``filename`` its local name.
    """

    archive: str
    member: str
    filename: str

    def url(self, base_url: str = DEFAULT_BASE_URL) -> str:
        """The archive's full address under ``base_url``."""
        return base_url.rstrip("/") + "/" + self.archive

    @property
    def archive_name(self) -> str:
        """The archive's file name (last part of its address)."""
        return self.archive.rsplit("/", 1)[-1]


@dataclass(frozen=True, slots=True)
class ScanInfo:
    """One benchmark scan.

    Attributes:
        name: registry key, ``<site>_station<k>`` (``..._reduced`` for reduced-8 scans).
        split: the split the scan belongs to (training scans serve both challenges).
        points: the ASCII points file (``x y z intensity r g b`` per line).
        labels: the ground-truth ``.labels`` file; ``None`` for test scans (withheld).
        submission_name: the official name of this scan's result file in a submission;
            ``None`` for training scans.
        n_points: number of points (lines), where a public source states it; else ``None``.
        reduced_from: for reduced-8 scans, the semantic-8 scan they were sub-sampled from.
    """

    name: str
    split: Split
    points: ArchiveFile
    labels: ArchiveFile | None = None
    submission_name: str | None = None
    n_points: int | None = None
    reduced_from: str | None = None

    @property
    def stem(self) -> str:
        """The local file stem shared by the points and labels files."""
        return self.points.filename.removesuffix(".txt")

    @property
    def files(self) -> tuple[ArchiveFile, ...]:
        """The files that make this scan complete on disk (points, then labels if any)."""
        return (self.points,) if self.labels is None else (self.points, self.labels)


def _train(stem: str, *, member: str | None = None) -> ScanInfo:
    name = stem.replace("_xyz_intensity_rgb", "").replace("_intensity_rgb", "")
    return ScanInfo(
        name=name,
        split=Split.TRAIN,
        points=ArchiveFile(
            archive=f"point-clouds/training1/{stem}.7z",
            member=member or f"{stem}.txt",
            filename=f"{stem}.txt",
        ),
        labels=ArchiveFile(
            archive=LABELS_ARCHIVE, member=f"{stem}.labels", filename=f"{stem}.labels"
        ),
    )


def _semantic8(stem: str, short: str, n_points: int) -> ScanInfo:
    name = stem.replace("_xyz_intensity_rgb", "").replace("_intensity_rgb", "")
    return ScanInfo(
        name=name,
        split=Split.SEMANTIC_8,
        points=ArchiveFile(
            archive=f"point-clouds/testing1/{stem}.7z",
            member=f"{stem}.txt",
            filename=f"{stem}.txt",
        ),
        submission_name=f"{short}.labels",
        n_points=n_points,
    )


def _reduced8(stem: str, short: str, n_points: int, *, reduced_from: str) -> ScanInfo:
    return ScanInfo(
        name=f"{reduced_from}_reduced",
        split=Split.REDUCED_8,
        points=ArchiveFile(
            archive=f"point-clouds/testing2/{stem}.txt.7z",
            member=f"{stem}.txt",
            filename=f"{stem}.txt",
        ),
        submission_name=f"{short}-reduced.labels",
        n_points=n_points,
        reduced_from=reduced_from,
    )


# Order: as the benchmark lists them (alphabetical by file stem within each split).
_SCANS: tuple[ScanInfo, ...] = (
    _train("bildstein_station1_xyz_intensity_rgb"),
    _train("bildstein_station3_xyz_intensity_rgb"),
    _train("bildstein_station5_xyz_intensity_rgb"),
    _train("domfountain_station1_xyz_intensity_rgb"),
    _train("domfountain_station2_xyz_intensity_rgb"),
    _train("domfountain_station3_xyz_intensity_rgb"),
    # The archive's file lacks the site prefix; the labels file has it.
    _train("neugasse_station1_xyz_intensity_rgb", member="station1_xyz_intensity_rgb.txt"),
    _train("sg27_station1_intensity_rgb"),
    _train("sg27_station2_intensity_rgb"),
    _train("sg27_station4_intensity_rgb"),
    _train("sg27_station5_intensity_rgb"),
    _train("sg27_station9_intensity_rgb"),
    _train("sg28_station4_intensity_rgb"),
    _train("untermaederbrunnen_station1_xyz_intensity_rgb"),
    _train("untermaederbrunnen_station3_xyz_intensity_rgb"),
    # semantic-8: point counts from PointCNN's evaluation/semantic3d_merge.py.
    _semantic8("birdfountain_station1_xyz_intensity_rgb", "birdfountain1", 40_133_912),
    _semantic8("castleblatten_station1_intensity_rgb", "castleblatten1", 31_806_225),
    _semantic8("castleblatten_station5_xyz_intensity_rgb", "castleblatten5", 49_152_311),
    _semantic8("marketplacefeldkirch_station1_intensity_rgb", "marketsquarefeldkirch1", 26_884_140),
    _semantic8("marketplacefeldkirch_station4_intensity_rgb", "marketsquarefeldkirch4", 23_137_668),
    _semantic8("marketplacefeldkirch_station7_intensity_rgb", "marketsquarefeldkirch7", 23_419_114),
    _semantic8("sg27_station10_intensity_rgb", "sg27_10", 285_579_196),
    _semantic8("sg27_station3_intensity_rgb", "sg27_3", 422_445_052),
    _semantic8("sg27_station6_intensity_rgb", "sg27_6", 226_790_878),
    _semantic8("sg27_station8_intensity_rgb", "sg27_8", 429_615_314),
    _semantic8("sg28_station2_intensity_rgb", "sg28_2", 170_158_281),
    _semantic8("sg28_station5_xyz_intensity_rgb", "sg28_5", 267_520_082),
    _semantic8("stgallencathedral_station1_intensity_rgb", "stgallencathedral1", 31_179_769),
    _semantic8("stgallencathedral_station3_intensity_rgb", "stgallencathedral3", 31_643_853),
    _semantic8("stgallencathedral_station6_intensity_rgb", "stgallencathedral6", 32_486_227),
    # reduced-8: sub-sampled copies of four semantic-8 scans.
    _reduced8(
        "MarketplaceFeldkirch_Station4_rgb_intensity-reduced",
        "marketsquarefeldkirch4",
        10_538_633,
        reduced_from="marketplacefeldkirch_station4",
    ),
    _reduced8(
        "StGallenCathedral_station6_rgb_intensity-reduced",
        "stgallencathedral6",
        14_608_690,
        reduced_from="stgallencathedral_station6",
    ),
    _reduced8(
        "sg27_station10_rgb_intensity-reduced",
        "sg27_10",
        28_931_322,
        reduced_from="sg27_station10",
    ),
    _reduced8(
        "sg28_Station2_rgb_intensity-reduced",
        "sg28_2",
        24_620_684,
        reduced_from="sg28_station2",
    ),
)

#: The fold of each training scan (in registry order, which is the sorted order of the file
#: stems) in the split that KPConv (Thomas et al. 2019, ``datasets/Semantic3D.py``),
#: RandLA-Net (Hu et al. 2020, ``main_Semantic3D.py``: "Following KPConv to do the
#: train-validation split") and Open3D-ML (``ml3d/datasets/semantic3d.py``) share.
REFERENCE_FOLDS: tuple[int, ...] = (0, 1, 4, 5, 3, 4, 3, 0, 1, 2, 3, 4, 2, 0, 5)

#: The fold those projects validate on: bildstein_station3 and sg27_station2 (Open3D-ML's
#: ``val_files``); they train on the other 13.
REFERENCE_VALIDATION_FOLD = 1


def reference_split() -> tuple[tuple[ScanInfo, ...], tuple[ScanInfo, ...]]:
    """``(training, validation)`` scans of KPConv's / RandLA-Net's / Open3D-ML's split.

    Train on the 13 and validate on the 2 to compare numbers with theirs.

    >>> training, validation = reference_split()
    >>> len(training), [info.name for info in validation]
    (13, ['bildstein_station3', 'sg27_station2'])
    """
    train = scans(Split.TRAIN)
    chosen = [fold == REFERENCE_VALIDATION_FOLD for fold in REFERENCE_FOLDS]
    return (
        tuple(info for info, held in zip(train, chosen, strict=True) if not held),
        tuple(info for info, held in zip(train, chosen, strict=True) if held),
    )


_BY_NAME: dict[str, ScanInfo] = {info.name: info for info in _SCANS}
_BY_STEM: dict[str, ScanInfo] = {info.stem: info for info in _SCANS}


def _as_split(value: Split | str, *, what: str = "split") -> Split:
    if isinstance(value, Split):
        return value
    try:
        return Split(value)
    except ValueError:
        expected = ", ".join(split.value for split in Split)
        raise UnknownScanError(
            f"unknown {what}: expected one of {expected}, found {value!r}"
        ) from None


def scans(split: Split | str | None = None) -> tuple[ScanInfo, ...]:
    """The registry's scans in ``split`` (every scan when ``split`` is ``None``), in order.

    >>> len(scans(Split.TRAIN)), len(scans("semantic-8")), len(scans("reduced-8"))
    (15, 15, 4)
    """
    if split is None:
        return _SCANS
    wanted = _as_split(split)
    return tuple(info for info in _SCANS if info.split is wanted)


def scan(name: str) -> ScanInfo:
    """The scan called ``name``: its registry name or its local file stem.

    >>> scan("sg27_station1").points.filename
    'sg27_station1_intensity_rgb.txt'
    >>> scan("sg27_station1_intensity_rgb").name
    'sg27_station1'
    """
    found = _BY_NAME.get(name) or _BY_STEM.get(name)
    if found is None:
        raise UnknownScanError(
            f"unknown scan: expected a registry name such as 'bildstein_station1' "
            f"or a file stem such as 'bildstein_station1_xyz_intensity_rgb', found {name!r}"
        )
    return found


def submission_name(name: str, challenge: Split | str) -> str:
    """The file name under which a submission to ``challenge`` holds the labels of a scan.

    For ``reduced-8`` the semantic-8 scan a reduced scan was made from may be named too.

    >>> submission_name("birdfountain_station1", "semantic-8")
    'birdfountain1.labels'
    >>> submission_name("sg28_station2_reduced", "reduced-8")
    'sg28_2-reduced.labels'
    """
    wanted = _as_split(challenge, what="challenge")
    if not wanted.is_challenge:
        raise UnknownScanError(
            "unknown challenge: expected semantic-8 or reduced-8, found 'train' "
            "(training scans are not submitted)"
        )
    info = scan(name)
    if info.split is not wanted and wanted is Split.REDUCED_8:
        reduced = [other for other in scans(Split.REDUCED_8) if other.reduced_from == info.name]
        if reduced:
            info = reduced[0]
    if info.split is not wanted or info.submission_name is None:
        raise UnknownScanError(
            f"scan {info.name!r}: expected a scan of challenge {wanted.value}, "
            f"found a {info.split.value} scan"
        )
    return info.submission_name
