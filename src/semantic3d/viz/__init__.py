"""Plots, palettes and cube-map renders; matplotlib (the ``[viz]`` extra) is imported only when
plotting."""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.viz.cubemap import CubeMap, CubeMapError, project_points, render_cubemap
    from semantic3d.viz.plots import (
        figure_to_png,
        plot_agreement,
        plot_class_histogram,
        plot_confusion_heatmap,
        plot_iou_bars,
    )

__all__ = [
    "CubeMap",
    "CubeMapError",
    "figure_to_png",
    "plot_agreement",
    "plot_class_histogram",
    "plot_confusion_heatmap",
    "plot_iou_bars",
    "project_points",
    "render_cubemap",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "CubeMap": "semantic3d.viz.cubemap",
        "CubeMapError": "semantic3d.viz.cubemap",
        "project_points": "semantic3d.viz.cubemap",
        "render_cubemap": "semantic3d.viz.cubemap",
        "figure_to_png": "semantic3d.viz.plots",
        "plot_agreement": "semantic3d.viz.plots",
        "plot_class_histogram": "semantic3d.viz.plots",
        "plot_confusion_heatmap": "semantic3d.viz.plots",
        "plot_iou_bars": "semantic3d.viz.plots",
    },
)
