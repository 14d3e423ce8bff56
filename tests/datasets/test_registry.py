"""The scan registry: counts, names, archive addresses, submission names, the known traps."""

from __future__ import annotations

import doctest
from collections import Counter

import pytest

import semantic3d.datasets.archive
import semantic3d.datasets.registry
import semantic3d.datasets.semantic3d
from semantic3d.core.errors import Semantic3DError
from semantic3d.datasets.registry import (
    DEFAULT_BASE_URL,
    LABELS_ARCHIVE,
    ScanInfo,
    Split,
    UnknownScanError,
    scan,
    scans,
    submission_name,
)

# The submission names as published by RandLA-Net (main_Semantic3D.py) and KPConv
# (datasets/Semantic3D.py), keyed by the test scan's file stem.
PUBLISHED_SUBMISSION_NAMES = {
    "MarketplaceFeldkirch_Station4_rgb_intensity-reduced": "marketsquarefeldkirch4-reduced.labels",
    "sg27_station10_rgb_intensity-reduced": "sg27_10-reduced.labels",
    "sg28_Station2_rgb_intensity-reduced": "sg28_2-reduced.labels",
    "StGallenCathedral_station6_rgb_intensity-reduced": "stgallencathedral6-reduced.labels",
    "birdfountain_station1_xyz_intensity_rgb": "birdfountain1.labels",
    "castleblatten_station1_intensity_rgb": "castleblatten1.labels",
    "castleblatten_station5_xyz_intensity_rgb": "castleblatten5.labels",
    "marketplacefeldkirch_station1_intensity_rgb": "marketsquarefeldkirch1.labels",
    "marketplacefeldkirch_station4_intensity_rgb": "marketsquarefeldkirch4.labels",
    "marketplacefeldkirch_station7_intensity_rgb": "marketsquarefeldkirch7.labels",
    "sg27_station10_intensity_rgb": "sg27_10.labels",
    "sg27_station3_intensity_rgb": "sg27_3.labels",
    "sg27_station6_intensity_rgb": "sg27_6.labels",
    "sg27_station8_intensity_rgb": "sg27_8.labels",
    "sg28_station2_intensity_rgb": "sg28_2.labels",
    "sg28_station5_xyz_intensity_rgb": "sg28_5.labels",
    "stgallencathedral_station1_intensity_rgb": "stgallencathedral1.labels",
    "stgallencathedral_station3_intensity_rgb": "stgallencathedral3.labels",
    "stgallencathedral_station6_intensity_rgb": "stgallencathedral6.labels",
}


def test_split_sizes() -> None:
    assert len(scans(Split.TRAIN)) == 15
    assert len(scans(Split.SEMANTIC_8)) == 15
    assert len(scans(Split.REDUCED_8)) == 4
    assert len(scans()) == 34
    assert {info.split for info in scans()} == set(Split)


def test_split_accepts_its_string_value() -> None:
    assert scans("semantic-8") == scans(Split.SEMANTIC_8)


@pytest.mark.parametrize(
    "attribute",
    [
        lambda info: info.name,
        lambda info: info.stem,
        lambda info: info.points.filename,
        lambda info: info.points.archive,
    ],
    ids=["name", "stem", "points filename", "archive"],
)
def test_identifiers_are_unique(attribute) -> None:
    counts = Counter(attribute(info) for info in scans())
    assert [value for value, count in counts.items() if count > 1] == []


def test_local_file_names_are_unique_across_all_files() -> None:
    names = [item.filename for info in scans() for item in info.files]
    assert len(names) == len(set(names)) == 34 + 15


def test_submission_names_match_the_published_table() -> None:
    found = {info.stem: info.submission_name for info in scans() if info.split.is_challenge}
    assert found == PUBLISHED_SUBMISSION_NAMES
    assert all(info.submission_name is None for info in scans(Split.TRAIN))


def test_feldkirch_data_says_marketplace_but_submissions_say_marketsquare() -> None:
    feldkirch = [info for info in scans() if "feldkirch" in info.name]
    assert len(feldkirch) == 4  # stations 1, 4, 7 and the reduced station 4
    for info in feldkirch:
        assert info.stem.lower().startswith("marketplacefeldkirch")
        assert "marketplace" in info.points.archive.lower()
        assert info.submission_name is not None
        assert info.submission_name.startswith("marketsquarefeldkirch")


def test_neugasse_archive_member_is_renamed_to_the_labelled_name() -> None:
    info = scan("neugasse_station1")
    assert info.points.archive == "point-clouds/training1/neugasse_station1_xyz_intensity_rgb.7z"
    assert info.points.member == "station1_xyz_intensity_rgb.txt"
    assert info.points.filename == "neugasse_station1_xyz_intensity_rgb.txt"
    assert info.labels is not None
    assert (
        info.labels.member == info.labels.filename == "neugasse_station1_xyz_intensity_rgb.labels"
    )
    renamed = [info.name for info in scans() if info.points.member != info.points.filename]
    assert renamed == ["neugasse_station1"]


def test_training_labels_come_from_the_shared_archive() -> None:
    for info in scans(Split.TRAIN):
        assert info.labels is not None
        assert info.labels.archive == LABELS_ARCHIVE
        assert info.labels.filename == info.stem + ".labels"
    assert all(info.labels is None for info in scans() if info.split.is_challenge)


@pytest.mark.parametrize(
    ("split", "folder", "suffix"),
    [
        (Split.TRAIN, "point-clouds/training1/", ".7z"),
        (Split.SEMANTIC_8, "point-clouds/testing1/", ".7z"),
        (Split.REDUCED_8, "point-clouds/testing2/", ".txt.7z"),
    ],
)
def test_archive_addresses(split: Split, folder: str, suffix: str) -> None:
    for info in scans(split):
        assert info.points.archive == f"{folder}{info.stem}{suffix}"
        assert info.points.url() == f"{DEFAULT_BASE_URL}{folder}{info.stem}{suffix}"


def test_url_joins_a_mirror_with_or_without_trailing_slash() -> None:
    points = scan("bildstein_station1").points
    expected = (
        "https://mirror.example/s3d/point-clouds/training1/bildstein_station1_xyz_intensity_rgb.7z"
    )
    assert points.url("https://mirror.example/s3d") == expected
    assert points.url("https://mirror.example/s3d/") == expected


def test_reduced_scans_name_their_semantic8_origin() -> None:
    for info in scans(Split.REDUCED_8):
        origin = scan(info.reduced_from or "")
        assert origin.split is Split.SEMANTIC_8
        assert info.name == f"{origin.name}_reduced"
        assert info.n_points is not None and origin.n_points is not None
        assert info.n_points < origin.n_points


def test_point_counts_of_test_scans() -> None:
    assert all(info.n_points is None for info in scans(Split.TRAIN))
    assert sum(info.n_points or 0 for info in scans(Split.SEMANTIC_8)) == 2_091_952_022
    assert scan("sg27_station8").n_points == 429_615_314


def test_scan_lookup_by_name_or_stem() -> None:
    by_name = scan("sg28_station2_reduced")
    assert scan("sg28_Station2_rgb_intensity-reduced") is by_name
    assert isinstance(by_name, ScanInfo)


def test_unknown_scan_is_a_lookup_error_naming_what_was_asked() -> None:
    with pytest.raises(UnknownScanError, match=r"unknown scan: .* found 'bildstein_station2'"):
        scan("bildstein_station2")
    assert issubclass(UnknownScanError, LookupError)
    assert issubclass(UnknownScanError, Semantic3DError)


@pytest.mark.parametrize(
    ("name", "challenge", "expected"),
    [
        ("birdfountain_station1", Split.SEMANTIC_8, "birdfountain1.labels"),
        ("marketplacefeldkirch_station7", "semantic-8", "marketsquarefeldkirch7.labels"),
        (
            "marketplacefeldkirch_station4_reduced",
            "reduced-8",
            "marketsquarefeldkirch4-reduced.labels",
        ),
        ("marketplacefeldkirch_station4", "reduced-8", "marketsquarefeldkirch4-reduced.labels"),
        ("stgallencathedral_station6", Split.REDUCED_8, "stgallencathedral6-reduced.labels"),
        ("sg27_station10_intensity_rgb", "semantic-8", "sg27_10.labels"),
    ],
)
def test_submission_name(name: str, challenge: Split | str, expected: str) -> None:
    assert submission_name(name, challenge) == expected


@pytest.mark.parametrize(
    ("name", "challenge", "message"),
    [
        (
            "bildstein_station1",
            "semantic-8",
            "expected a scan of challenge semantic-8, found a train",
        ),
        (
            "birdfountain_station1",
            "reduced-8",
            "expected a scan of challenge reduced-8, found a semantic-8",
        ),
        ("sg27_station10_reduced", "semantic-8", "found a reduced-8 scan"),
        ("birdfountain_station1", "train", "expected semantic-8 or reduced-8, found 'train'"),
        (
            "birdfountain_station1",
            "semantic-3",
            "unknown challenge: expected one of .* found 'semantic-3'",
        ),
        ("nowhere_station1", "semantic-8", "unknown scan"),
    ],
)
def test_submission_name_errors(name: str, challenge: str, message: str) -> None:
    with pytest.raises(UnknownScanError, match=message):
        submission_name(name, challenge)


def test_unknown_split_is_refused() -> None:
    with pytest.raises(
        UnknownScanError,
        match="unknown split: expected one of train, semantic-8, reduced-8, found 'test'",
    ):
        scans("test")


@pytest.mark.parametrize(
    "module",
    [semantic3d.datasets.registry, semantic3d.datasets.archive, semantic3d.datasets.semantic3d],
    ids=lambda module: module.__name__,
)
def test_doctests(module) -> None:
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0
    assert result.failed == 0


@pytest.mark.parametrize("challenge", [Split.SEMANTIC_8, Split.REDUCED_8])
def test_registry_agrees_with_the_evaluation_protocol(challenge: Split) -> None:
    protocol = pytest.importorskip("semantic3d.evaluation.protocol")
    spec = protocol.load_protocol(protocol.CURRENT_PROTOCOL_VERSION).challenges[challenge.value]
    in_protocol = {(s.name, s.submission_name, s.n_points) for s in spec.scans}
    in_registry = {(s.stem, s.submission_name, s.n_points) for s in scans(challenge)}
    assert in_registry == in_protocol
