"""Reports of an :class:`EvaluationResult`: JSON, Markdown and a self-contained HTML page.

Tables are laid out like Tables 1-2 of the semantic3D.net paper: method, mIoU, OA, T
(runtime), then IoU of classes 1..8. Absent classes read "absent" (never 0). The HTML
page embeds its plots as base64 PNGs and its style inline: one file, no external assets.
Per-scan scores are private and appear in no report; they are only in the full JSON.
"""

from __future__ import annotations

import base64
import html
import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from semantic3d.core.classes import CLASSES
from semantic3d.evaluation.result import EvaluationResult
from semantic3d.viz.plots import figure_to_png, plot_confusion_heatmap, plot_iou_bars

ABSENT = "absent"


def _number(value: float) -> str:
    return ABSENT if math.isnan(value) else f"{value:.3f}"


def _runtime(result: EvaluationResult) -> str:
    method = result.method
    if method is None or method.runtime_s is None:
        return "–"
    return f"{method.runtime_s:.0f} s"


def _method_name(result: EvaluationResult) -> str:
    return result.method.name if result.method is not None else "(unnamed)"


def results_table_rows(results: Sequence[EvaluationResult]) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the paper's results table (method, mIoU, OA, T, IoU_1..8)."""
    header = ["Method", "mIoU", "OA", "T", *(f"IoU {c.value} {c.name}" for c in CLASSES)]
    rows = [
        [
            _method_name(r),
            _number(r.scores.mean_iou),
            _number(r.scores.overall_accuracy),
            _runtime(r),
            *(_number(float(v)) for v in r.scores.iou),
        ]
        for r in results
    ]
    return header, rows


def _markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def format_results_table(results: Sequence[EvaluationResult]) -> str:
    """Markdown table of several results, ordered as given (e.g. a leaderboard)."""
    return _markdown_table(*results_table_rows(results))


def _class_rows(result: EvaluationResult) -> list[list[str]]:
    s = result.scores
    counts = result.confusion.sum(axis=1)
    return [
        [
            f"{cls.value} {cls.name}",
            str(int(counts[cls.index])),
            _number(float(s.iou[cls.index])),
            _number(float(s.precision[cls.index])),
            _number(float(s.recall[cls.index])),
            _number(float(s.f1[cls.index])),
        ]
        for cls in CLASSES
    ]


def _absent_note(result: EvaluationResult) -> str:
    absent = [CLASSES[i].name for i in result.scores.absent_indices]
    if not absent:
        return "All 8 classes are present."
    return (
        f"Absent from both ground truth and prediction, left out of the mean: {', '.join(absent)}."
    )


def render_markdown(result: EvaluationResult) -> str:
    """A Markdown report: results table, per-class scores, confusion matrix."""
    names = [c.name for c in CLASSES]
    matrix_rows = [[names[i], *map(str, row)] for i, row in enumerate(result.confusion.tolist())]
    parts = [
        f"# Evaluation: {_method_name(result)} on {result.challenge}",
        "",
        f"Protocol v{result.protocol_version}, {result.n_points} labelled points, "
        f"semantic3d {result.software_version}. {_absent_note(result)}",
        "",
        format_results_table([result]),
        "",
        "## Per class",
        "",
        _markdown_table(
            ["Class", "Points", "IoU", "Precision", "Recall", "F1"], _class_rows(result)
        ),
        "",
        "## Confusion matrix (rows: ground truth, columns: prediction)",
        "",
        _markdown_table(["", *names], matrix_rows),
        "",
    ]
    return "\n".join(parts)


def _html_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(cell)}</td>" for cell in row) + "</tr>" for row in rows
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _png_tag(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 72em; color: #222; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #bbb; padding: 0.3em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
thead th { background: #eee; }
img { max-width: 100%; display: block; margin: 1em 0; }
.note { color: #555; }
"""


def render_html(result: EvaluationResult) -> str:
    """A self-contained HTML page: results table, per-class scores, heatmap, IoU bars."""
    s = result.scores
    heatmap = figure_to_png(plot_confusion_heatmap(result.confusion))
    bars = figure_to_png(
        plot_iou_bars(s.iou, mean_iou=None if np.isnan(s.mean_iou) else s.mean_iou)
    )
    title = f"Evaluation: {_method_name(result)} on {result.challenge}"
    method = result.method
    meta = [
        f"Protocol v{result.protocol_version}",
        f"{result.n_points} labelled points",
        f"semantic3d {result.software_version}",
    ]
    if method is not None and method.hardware:
        meta.append(f"hardware: {method.hardware}")
    links = ""
    if method is not None:
        for label, url in (("paper", method.paper_url), ("code", method.code_url)):
            if url:
                links += f' <a href="{html.escape(url)}">{label}</a>'
    return "\n".join(
        [
            "<!DOCTYPE html>",
            '<html lang="en"><head><meta charset="utf-8">',
            f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>",
            f"<h1>{html.escape(title)}</h1>",
            f'<p class="note">{html.escape(", ".join(meta))}.{links}</p>',
            f'<p class="note">{html.escape(_absent_note(result))}</p>',
            _html_table(*results_table_rows([result])),
            "<h2>Per class</h2>",
            _html_table(
                ["Class", "Points", "IoU", "Precision", "Recall", "F1"], _class_rows(result)
            ),
            "<h2>Confusion matrix</h2>",
            '<p class="note">Rows: ground truth; columns: prediction; '
            "cells: share of the true class (%).</p>",
            _png_tag(heatmap, "confusion matrix heatmap"),
            "<h2>IoU per class</h2>",
            _png_tag(bars, "IoU per class"),
            "</body></html>",
            "",
        ]
    )


def write_json(path: Path, result: EvaluationResult, *, include_per_scan: bool = True) -> None:
    """Write ``result.to_dict()`` (or the public form) as indented JSON (NaN as null)."""
    data = result.to_dict() if include_per_scan else result.to_public_dict()
    path.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")


def write_markdown(path: Path, result: EvaluationResult) -> None:
    """Write :func:`render_markdown` to ``path``."""
    path.write_text(render_markdown(result), encoding="utf-8")


def write_html(path: Path, result: EvaluationResult) -> None:
    """Write :func:`render_html` to ``path``."""
    path.write_text(render_html(result), encoding="utf-8")
