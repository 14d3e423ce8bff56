"""Names of the feature columns: ``<feature>@<voxel size>m``, e.g. ``planarity@0.100m``.

Columns are always named, never positional. The order is level-major: every feature of
the finest pyramid level, then every feature of the next level, and so on. Within a level,
the order is the covariance and moment columns, the spherical height columns, the
cylinder height columns, then the optional colour and intensity columns.

>>> column_name("planarity", 0.1)
'planarity@0.100m'
>>> parse_column_name("planarity@0.100m")
('planarity', 0.1)
"""

from __future__ import annotations

from collections.abc import Sequence

COVARIANCE_FEATURES: tuple[str, ...] = (
    "sum_of_eigenvalues",
    "omnivariance",
    "eigenentropy",
    "anisotropy",
    "planarity",
    "linearity",
    "surface_variation",
    "sphericity",
    "verticality",
)
"""Features of the eigenvalues / eigenvectors of the neighbourhood covariance (Hackel 2016)."""

MOMENT_FEATURES: tuple[str, ...] = (
    "moment1_axis1",
    "moment1_axis2",
    "moment2_axis1",
    "moment2_axis2",
)
"""First and second order moments of the neighbours about the query point along the first
two eigenvectors (first-order moments as absolute values: eigenvector signs are arbitrary)."""

HEIGHT_FEATURES: tuple[str, ...] = ("vertical_range", "height_below", "height_above")
"""``z_max - z_min``, ``z - z_min`` and ``z_max - z`` over the neighbourhood."""

GEOMETRIC_FEATURES: tuple[str, ...] = COVARIANCE_FEATURES + MOMENT_FEATURES + HEIGHT_FEATURES
"""The 16 per-level features of the k nearest neighbours, in column order."""

CYLINDER_FEATURES: tuple[str, ...] = (
    "cylinder_range",
    "cylinder_below",
    "cylinder_above",
    "cylinder_points",
)
"""Height features of a vertical cylinder about the query (:mod:`~semantic3d.features.cylinders`):
``z_max - z_min``, ``z - z_min``, ``z_max - z`` and the number of level points in it."""

COLOUR_FEATURES: tuple[str, ...] = ("hue", "saturation", "value")
"""HSV of the mean neighbourhood colour (optional, off by default)."""

INTENSITY_FEATURES: tuple[str, ...] = ("intensity",)
"""Mean neighbourhood intensity (optional, off by default)."""

_SEPARATOR = "@"


def level_feature_names(
    *,
    colour: bool = False,
    intensity: bool = False,
    spherical_height: bool = True,
    cylinders: Sequence[str] = (),
) -> tuple[str, ...]:
    """The per-level feature names, in column order (``cylinders``: the cylinder columns
    kept, a subsequence of :data:`CYLINDER_FEATURES`)."""
    names = COVARIANCE_FEATURES + MOMENT_FEATURES
    if spherical_height:
        names += HEIGHT_FEATURES
    names += tuple(cylinders)
    if colour:
        names += COLOUR_FEATURES
    if intensity:
        names += INTENSITY_FEATURES
    return names


def column_name(feature: str, voxel_size_m: float) -> str:
    """The column of ``feature`` at the pyramid level of voxel size ``voxel_size_m``."""
    return f"{feature}{_SEPARATOR}{voxel_size_m:.3f}m"


def parse_column_name(name: str) -> tuple[str, float]:
    """``(feature, voxel_size_m)`` of a column name; raises ``ValueError`` on another shape."""
    feature, sep, scale = name.rpartition(_SEPARATOR)
    if not sep or not feature or not scale.endswith("m"):
        raise ValueError(f"feature column {name!r}: expected '<feature>@<size>m'")
    try:
        return feature, float(scale[:-1])
    except ValueError:
        raise ValueError(f"feature column {name!r}: expected '<feature>@<size>m'") from None


def column_names(
    voxel_sizes_m: Sequence[float],
    *,
    colour: bool = False,
    intensity: bool = False,
    spherical_height: bool = True,
    cylinders: Sequence[str] = (),
) -> tuple[str, ...]:
    """All column names for the pyramid levels of ``voxel_sizes_m`` (level-major order)."""
    per_level = level_feature_names(
        colour=colour, intensity=intensity, spherical_height=spherical_height, cylinders=cylinders
    )
    return tuple(column_name(f, size) for size in voxel_sizes_m for f in per_level)
