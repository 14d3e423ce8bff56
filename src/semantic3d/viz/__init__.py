"""Plots and palettes; matplotlib (the ``[viz]`` extra) is imported only when plotting."""

from semantic3d.viz.plots import (
    figure_to_png,
    plot_agreement,
    plot_class_histogram,
    plot_confusion_heatmap,
    plot_iou_bars,
)

__all__ = [
    "figure_to_png",
    "plot_agreement",
    "plot_class_histogram",
    "plot_confusion_heatmap",
    "plot_iou_bars",
]
