"""Plots of the benchmark's analyses: confusion heatmap, IoU bars, points per class.

Figures are built with matplotlib's object API on the Agg canvas (no pyplot state, no
display needed) and returned; :func:`figure_to_png` renders one to PNG bytes. Class
colours come from :mod:`semantic3d.core.classes`. matplotlib is the ``[viz]`` extra.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from semantic3d.core.classes import CLASSES
from semantic3d.core.errors import ShapeError, require

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def _figure(width_in: float, height_in: float) -> Figure:
    require("matplotlib", "viz")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _class_names(n_classes: int, class_names: Sequence[str] | None) -> list[str]:
    if class_names is not None:
        if len(class_names) != n_classes:
            raise ShapeError(f"class_names: expected {n_classes} names, found {len(class_names)}")
        return list(class_names)
    if n_classes == len(CLASSES):
        return [cls.name for cls in CLASSES]
    return [str(value) for value in range(1, n_classes + 1)]


def _class_colours(n_classes: int) -> list[str]:
    if n_classes == len(CLASSES):
        return [cls.hex_colour for cls in CLASSES]
    return ["#4c72b0"] * n_classes


def _hatch_legend(labels: Sequence[str], hatches: Sequence[str]) -> list[Any]:
    """Legend entries telling groups apart by hatch (bar colours are the classes')."""
    from matplotlib.patches import Patch

    return [
        Patch(facecolor="white", edgecolor="black", hatch=hatches[k % len(hatches)], label=label)
        for k, label in enumerate(labels)
    ]


def figure_to_png(figure: Figure, *, dpi: int = 110) -> bytes:
    """Render ``figure`` to PNG bytes."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()


def plot_confusion_heatmap(
    matrix: ArrayLike,
    *,
    class_names: Sequence[str] | None = None,
    title: str = "Confusion matrix",
) -> Figure:
    """Heatmap of a confusion matrix (rows ground truth, columns prediction).

    Colours show each row normalised to 1 (the share of a true class given to each
    predicted class); cells carry that share in percent. Empty rows stay blank.
    """
    counts = np.asarray(matrix, dtype=np.float64)
    if counts.ndim != 2 or counts.shape[0] != counts.shape[1]:
        raise ShapeError(f"matrix: expected a square (n, n) array, found shape {counts.shape}")
    n = counts.shape[0]
    names = _class_names(n, class_names)
    rows = counts.sum(axis=1, keepdims=True)
    share = np.divide(counts, rows, out=np.full_like(counts, np.nan), where=rows > 0)
    figure = _figure(1.6 + 0.75 * n, 1.2 + 0.65 * n)
    axes = figure.add_subplot()
    image = axes.imshow(share, cmap="Blues", vmin=0.0, vmax=1.0)
    for i in range(n):
        for j in range(n):
            if np.isfinite(share[i, j]) and counts[i, j] > 0:
                colour = "white" if share[i, j] > 0.6 else "black"
                axes.text(
                    j,
                    i,
                    f"{100 * share[i, j]:.1f}",
                    ha="center",
                    va="center",
                    fontsize=8,
                    color=colour,
                )
    axes.set_xticks(range(n), names, rotation=45, ha="right")
    axes.set_yticks(range(n), names)
    axes.set_xlabel("prediction")
    axes.set_ylabel("ground truth")
    axes.set_title(title)
    figure.colorbar(image, ax=axes, label="share of the true class", shrink=0.8)
    return figure


def plot_iou_bars(
    iou: ArrayLike,
    *,
    mean_iou: float | None = None,
    class_names: Sequence[str] | None = None,
    title: str = "IoU per class",
) -> Figure:
    """Bar chart of per-class IoU in class colours; absent classes (NaN) are marked."""
    values = np.asarray(iou, dtype=np.float64)
    if values.ndim != 1:
        raise ShapeError(f"iou: expected a 1-D array, found shape {values.shape}")
    n = values.shape[0]
    names = _class_names(n, class_names)
    figure = _figure(1.5 + 0.7 * n, 3.6)
    axes = figure.add_subplot()
    heights = np.nan_to_num(values, nan=0.0)
    axes.bar(range(n), heights, color=_class_colours(n), edgecolor="black", linewidth=0.5)
    for x, value in enumerate(values):
        label = "absent" if np.isnan(value) else f"{value:.3f}"
        axes.text(
            x, (0 if np.isnan(value) else value) + 0.01, label, ha="center", va="bottom", fontsize=8
        )
    if mean_iou is not None and np.isfinite(mean_iou):
        axes.axhline(mean_iou, color="black", linestyle="--", linewidth=1)
        # Outside the plot, right of the axis, so it never covers a bar's own label.
        axes.text(
            1.01,
            mean_iou,
            f"mIoU\n{mean_iou:.3f}",
            transform=axes.get_yaxis_transform(),
            ha="left",
            va="center",
            fontsize=8,
        )
    axes.set_ylim(0, 1.08)
    axes.set_xticks(range(n), names, rotation=45, ha="right")
    axes.set_ylabel("IoU")
    axes.set_title(title)
    return figure


def plot_class_histogram(
    counts_by_group: Mapping[str, ArrayLike],
    *,
    class_names: Sequence[str] | None = None,
    title: str = "Points per class",
) -> Figure:
    """Log-scale bar chart of points per class, one bar per group (split) and class.

    Args:
        counts_by_group: group name (e.g. ``"training"``) -> points per class index.
    """
    groups = list(counts_by_group)
    if not groups:
        raise ShapeError("counts_by_group: expected at least one group, found none")
    table = np.asarray([np.asarray(counts_by_group[g], dtype=np.float64) for g in groups])
    if table.ndim != 2:
        raise ShapeError("counts_by_group: expected equal-length 1-D arrays of counts")
    n = table.shape[1]
    names = _class_names(n, class_names)
    colours = _class_colours(n)
    figure = _figure(1.5 + 0.8 * n, 3.8)
    axes = figure.add_subplot()
    width = 0.8 / len(groups)
    hatches = ["", "//", "..", "xx", "\\\\", "++"]
    for k, group in enumerate(groups):
        offsets = np.arange(n) - 0.4 + width * (k + 0.5)
        heights = np.where(table[k] > 0, table[k], np.nan)
        axes.bar(
            offsets,
            heights,
            width=width,
            color=colours,
            edgecolor="black",
            linewidth=0.5,
            hatch=hatches[k % len(hatches)],
            label=group,
        )
    axes.set_yscale("log")
    if np.any(table > 0):
        axes.set_ylim(top=float(table.max()) * 30)  # headroom for the legend
    axes.set_xticks(range(n), names, rotation=45, ha="right")
    axes.set_ylabel("points (log scale)")
    axes.set_title(title)
    if len(groups) > 1:
        axes.legend(handles=_hatch_legend(groups, hatches))
    return figure


def plot_agreement(
    iou_by_direction: Mapping[str, ArrayLike],
    *,
    class_names: Sequence[str] | None = None,
    title: str = "Label agreement",
) -> Figure:
    """Per-class IoU of label transfer in each direction, side by side.

    Args:
        iou_by_direction: direction name (``"A→B"``) -> IoU per class index.
    """
    names_dirs = list(iou_by_direction)
    if not names_dirs:
        raise ShapeError("iou_by_direction: expected at least one direction, found none")
    ious = [np.asarray(iou_by_direction[d], dtype=np.float64) for d in names_dirs]
    n = ious[0].shape[0]
    names = _class_names(n, class_names)
    figure = _figure(1.5 + 0.8 * n, 3.8)
    axes = figure.add_subplot()
    width = 0.8 / len(names_dirs)
    hatches = ["", "//", "..", "xx"]
    for k, (direction, iou) in enumerate(zip(names_dirs, ious, strict=True)):
        offsets = np.arange(n) - 0.4 + width * (k + 0.5)
        axes.bar(
            offsets,
            np.nan_to_num(iou, nan=0.0),
            width=width,
            color=_class_colours(n),
            edgecolor="black",
            linewidth=0.5,
            hatch=hatches[k % len(hatches)],
            label=direction,
        )
        for x, value in zip(offsets, iou, strict=True):
            if np.isnan(value):
                axes.text(x, 0.01, "n/a", ha="center", va="bottom", fontsize=7, rotation=90)
    axes.set_ylim(0, 1.05)
    axes.set_xticks(range(n), names, rotation=45, ha="right")
    axes.set_ylabel("IoU of transferred labels")
    axes.set_title(title)
    axes.legend(handles=_hatch_legend(names_dirs, hatches))
    return figure
