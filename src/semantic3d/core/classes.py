"""The benchmark's class map: label value <-> name <-> display colour.

*Label values* are what files hold (0 unlabelled, 1..8 the classes). *Class indices*
(0..7) are rows and columns of a confusion matrix; convert with ``value - 1``. The two
never share a variable name in this package.

Colours follow the paper's figures: gray buildings, orange man-made terrain, green
natural terrain, yellow low vegetation, blue high vegetation, purple hard scape, pink
cars; scanning artefacts, absent from the figures, are red.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, slots=True)
class SemanticClass:
    """One class of the benchmark: its label value in files, name and display colour."""

    value: int
    name: str
    colour: tuple[int, int, int]

    @property
    def index(self) -> int:
        """Row/column of this class in a confusion matrix (``value - 1``); -1 for unlabelled."""
        return self.value - 1

    @property
    def hex_colour(self) -> str:
        """The colour as ``#rrggbb``."""
        r, g, b = self.colour
        return f"#{r:02x}{g:02x}{b:02x}"


UNLABELLED = SemanticClass(0, "unlabelled", (200, 200, 200))

CLASSES: tuple[SemanticClass, ...] = (
    SemanticClass(1, "man-made terrain", (255, 140, 0)),
    SemanticClass(2, "natural terrain", (34, 139, 34)),
    SemanticClass(3, "high vegetation", (30, 90, 230)),
    SemanticClass(4, "low vegetation", (240, 220, 0)),
    SemanticClass(5, "buildings", (128, 128, 128)),
    SemanticClass(6, "hard scape", (128, 0, 160)),
    SemanticClass(7, "scanning artefacts", (220, 20, 20)),
    SemanticClass(8, "cars", (255, 105, 180)),
)

N_CLASSES = len(CLASSES)
"""Number of benchmark classes (8); label values run 1..N_CLASSES."""

LABEL_VALUES: tuple[int, ...] = tuple(c.value for c in CLASSES)

_BY_VALUE = {c.value: c for c in (UNLABELLED, *CLASSES)}
_BY_NAME = {c.name: c for c in (UNLABELLED, *CLASSES)}


def class_by_value(value: int) -> SemanticClass:
    """The class with label value ``value`` (0 gives :data:`UNLABELLED`).

    >>> class_by_value(5).name
    'buildings'
    """
    try:
        return _BY_VALUE[int(value)]
    except KeyError:
        raise ValueError(f"label value {value} is not a class: expected 0..{N_CLASSES}") from None


def class_by_name(name: str) -> SemanticClass:
    """The class called ``name``; case, ``_`` and ``-`` are ignored.

    >>> class_by_name("High_Vegetation").value
    3
    """
    key = name.strip().lower().replace("_", " ").replace("-", " ")
    for cls in _BY_NAME.values():
        if cls.name.replace("-", " ") == key:
            return cls
    known = ", ".join(c.name for c in CLASSES)
    raise ValueError(f"unknown class name {name!r}: expected one of {known}")


def label_palette() -> NDArray[np.uint8]:
    """A ``(N_CLASSES + 1, 3)`` uint8 array: row ``v`` is the colour of label value ``v``."""
    palette = np.zeros((N_CLASSES + 1, 3), dtype=np.uint8)
    for cls in (UNLABELLED, *CLASSES):
        palette[cls.value] = cls.colour
    return palette
