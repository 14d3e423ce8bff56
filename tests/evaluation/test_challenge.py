"""Protocol file and challenges: official names, ground-truth lookup, the registry agreement."""

from __future__ import annotations

from pathlib import Path

import pytest

from semantic3d.core.classes import CLASSES
from semantic3d.core.errors import DataFormatError
from semantic3d.datasets import registry
from semantic3d.evaluation import (
    OFFICIAL_CHALLENGES,
    MissingGroundTruthError,
    custom_challenge,
    load_challenge,
    load_protocol,
)
from semantic3d.evaluation.protocol import parse_protocol


def test_protocol_classes_are_the_core_classes() -> None:
    protocol = load_protocol()
    assert protocol.version == "1"
    assert protocol.class_names == tuple(c.name for c in CLASSES)
    assert protocol.ignore_value == 0
    assert (protocol.prediction_min, protocol.prediction_max) == (1, 8)
    assert "rows are ground truth" in protocol.convention["matrix"]


@pytest.mark.parametrize("name", OFFICIAL_CHALLENGES)
def test_protocol_agrees_with_the_dataset_registry(name: str) -> None:
    """Scan names, submission names and point counts are written twice: keep them equal."""
    challenge = load_challenge(name, ground_truth_root=None)
    from_registry = {
        info.stem: (info.submission_name, info.n_points) for info in registry.scans(name)
    }
    from_protocol = {s.name: (s.submission_name, s.n_points) for s in challenge.scans}
    assert from_protocol == from_registry


def test_official_challenge_sizes() -> None:
    semantic = load_challenge("semantic-8", ground_truth_root=None)
    reduced = load_challenge("reduced-8", ground_truth_root=None)
    assert len(semantic.scans) == 15 and len(reduced.scans) == 4
    assert "marketsquarefeldkirch1.labels" in semantic.submission_names
    assert sum(s.n_points or 0 for s in reduced.scans) == 78_699_329
    assert not semantic.has_ground_truth


def test_unknown_challenge() -> None:
    with pytest.raises(ValueError, match="unknown challenge 'semantic-9': expected one of"):
        load_challenge("semantic-9", ground_truth_root=None)


def test_ground_truth_found_by_scan_name_or_submission_name(tmp_path: Path) -> None:
    reduced = load_challenge("reduced-8", ground_truth_root=None)
    first, *rest = reduced.scans
    (tmp_path / f"{first.name}.labels").write_bytes(b"1\n")
    for scan in rest:
        (tmp_path / scan.submission_name).write_bytes(b"1\n")
    challenge = load_challenge("reduced-8", ground_truth_root=tmp_path)
    assert challenge.has_ground_truth
    assert challenge.scans[0].ground_truth == tmp_path / f"{first.name}.labels"
    assert challenge.scans[1].ground_truth == tmp_path / rest[0].submission_name


def test_missing_ground_truth_lists_every_scan(tmp_path: Path) -> None:
    with pytest.raises(MissingGroundTruthError, match="missing 4: MarketplaceFeldkirch"):
        load_challenge("reduced-8", ground_truth_root=tmp_path)
    with pytest.raises(MissingGroundTruthError, match="expected a folder"):
        load_challenge("reduced-8", ground_truth_root=tmp_path / "nowhere")


def test_custom_challenge_is_every_labels_file(tmp_path: Path) -> None:
    for name in ("b.labels", "a.labels", "notes.txt", "._a.labels", ".b.1f2e3d4c.partial.labels"):
        (tmp_path / name).write_bytes(b"1\n")
    challenge = custom_challenge(tmp_path)
    assert challenge.submission_names == ("a.labels", "b.labels")  # hidden files are no scans
    assert challenge.name == f"custom:{tmp_path.name}"
    assert custom_challenge(tmp_path, name="mine").name == "mine"
    assert all(s.n_points is None for s in challenge.scans)


def test_custom_challenge_needs_labels(tmp_path: Path) -> None:
    with pytest.raises(MissingGroundTruthError, match="expected at least one"):
        custom_challenge(tmp_path)


def _protocol_data() -> dict:
    return {
        "version": "9",
        "benchmark": "b",
        "labels": {"ignore": 0, "prediction_min": 1, "prediction_max": 2, "classes": ["x", "y"]},
        "convention": {},
        "challenges": {"c": {"title": "t", "scans": [{"name": "s", "submission": "s.labels"}]}},
    }


def test_protocol_parsing_rejects_unknown_and_missing_keys() -> None:
    assert (
        parse_protocol(_protocol_data(), source="p.toml").challenges["c"].scans[0].n_points is None
    )
    data = _protocol_data()
    data["labels"]["colour"] = "red"
    with pytest.raises(DataFormatError, match=r"p.toml: \[labels\]: unknown keys \['colour'\]"):
        parse_protocol(data, source="p.toml")
    data = _protocol_data()
    del data["version"]
    with pytest.raises(DataFormatError, match=r"p.toml: missing keys \['version'\]"):
        parse_protocol(data, source="p.toml")
    data = _protocol_data()
    data["challenges"]["c"]["scans"].append({"name": "t", "submission": "s.labels"})
    with pytest.raises(DataFormatError, match="expected unique submission names"):
        parse_protocol(data, source="p.toml")


def test_unknown_protocol_version() -> None:
    with pytest.raises(DataFormatError, match=r"expected a packaged protocol_v0.toml"):
        load_protocol("0")


def test_package_doctest() -> None:
    import doctest

    import semantic3d.evaluation

    failures, tried = doctest.testmod(semantic3d.evaluation)
    assert (failures, tried) == (0, 2)
