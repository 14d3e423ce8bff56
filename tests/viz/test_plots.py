"""Plots render to PNG; bad shapes are rejected."""

from __future__ import annotations

import numpy as np
import pytest

from semantic3d.core.errors import ShapeError
from semantic3d.viz import (
    figure_to_png,
    plot_agreement,
    plot_class_histogram,
    plot_confusion_heatmap,
    plot_iou_bars,
)

PNG = b"\x89PNG\r\n\x1a\n"


def test_heatmap_labels_rows_ground_truth_and_shows_row_shares() -> None:
    matrix = np.zeros((8, 8), np.int64)
    matrix[0, 0], matrix[0, 1], matrix[4, 4] = 3, 1, 5
    figure = plot_confusion_heatmap(matrix)
    axes = figure.axes[0]
    assert axes.get_ylabel() == "ground truth" and axes.get_xlabel() == "prediction"
    assert axes.get_yticklabels()[0].get_text() == "man-made terrain"
    cells = sorted(t.get_text() for t in axes.texts)
    assert cells == ["100.0", "25.0", "75.0"]  # empty cells and empty rows stay blank
    assert figure_to_png(figure).startswith(PNG)


def test_iou_bars_mark_absent_classes() -> None:
    iou = np.array([0.5, np.nan, 1.0])
    figure = plot_iou_bars(iou, mean_iou=0.75, class_names=["a", "b", "c"])
    texts = [t.get_text() for t in figure.axes[0].texts]
    assert texts[:3] == ["0.500", "absent", "1.000"]
    assert "mIoU\n0.750" in texts
    assert figure_to_png(figure).startswith(PNG)


def test_class_histogram_is_log_scale_with_one_bar_per_split_and_class() -> None:
    counts = {"train": np.arange(1, 9) * 1000, "test": np.arange(8) * 10}
    figure = plot_class_histogram(counts)
    axes = figure.axes[0]
    assert axes.get_yscale() == "log"
    assert len(axes.patches) == 16
    assert [t.get_text() for t in axes.get_legend().get_texts()] == ["train", "test"]
    assert figure_to_png(figure).startswith(PNG)


def test_agreement_plot() -> None:
    figure = plot_agreement({"A→B": [1.0, 0.5] + [np.nan] * 6, "B→A": [0.9] * 8})
    assert len(figure.axes[0].patches) == 16
    assert figure_to_png(figure).startswith(PNG)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: plot_confusion_heatmap(np.zeros((2, 3))), r"expected a square \(n, n\) array"),
        (lambda: plot_iou_bars(np.zeros((2, 2))), "iou: expected a 1-D array"),
        (lambda: plot_iou_bars([0.1, 0.2], class_names=["a"]), "expected 2 names, found 1"),
        (lambda: plot_class_histogram({}), "expected at least one group"),
        (lambda: plot_agreement({}), "expected at least one direction"),
    ],
)
def test_bad_input(call: object, match: str) -> None:
    with pytest.raises(ShapeError, match=match):
        call()  # type: ignore[operator]
