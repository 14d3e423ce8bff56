from __future__ import annotations

import numpy as np
import pytest

from semantic3d.core import (
    CLASSES,
    N_CLASSES,
    UNLABELLED,
    class_by_name,
    class_by_value,
    label_palette,
)


def test_the_eight_benchmark_classes_in_order() -> None:
    assert N_CLASSES == 8
    assert [c.value for c in CLASSES] == list(range(1, 9))
    assert [c.name for c in CLASSES] == [
        "man-made terrain",
        "natural terrain",
        "high vegetation",
        "low vegetation",
        "buildings",
        "hard scape",
        "scanning artefacts",
        "cars",
    ]
    assert UNLABELLED.value == 0


def test_colours_are_distinct_and_follow_the_paper() -> None:
    colours = {c.colour for c in (UNLABELLED, *CLASSES)}
    assert len(colours) == 9
    buildings = class_by_name("buildings").colour
    assert buildings[0] == buildings[1] == buildings[2]  # gray
    r, g, b = class_by_name("man-made terrain").colour
    assert r > g > b  # orange
    assert class_by_name("high vegetation").colour[2] > 200  # blue


def test_lookup_by_value_and_name() -> None:
    assert class_by_value(8).name == "cars"
    assert class_by_value(0) is UNLABELLED
    assert class_by_name("Scanning_Artefacts").value == 7
    with pytest.raises(ValueError, match=r"label value 9 is not a class: expected 0\.\.8"):
        class_by_value(9)
    with pytest.raises(ValueError, match="unknown class name 'trees'"):
        class_by_name("trees")


def test_index_and_value_differ_by_one() -> None:
    assert [c.index for c in CLASSES] == list(range(8))
    assert UNLABELLED.index == -1


def test_palette_rows_are_label_values() -> None:
    palette = label_palette()
    assert palette.shape == (9, 3) and palette.dtype == np.uint8
    assert tuple(palette[5]) == class_by_value(5).colour
    assert class_by_value(3).hex_colour.startswith("#") and len(class_by_value(3).hex_colour) == 7
