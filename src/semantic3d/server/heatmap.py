"""The confusion matrix as an inline SVG heatmap (no plotting library needed in the server).

Rows are ground truth, columns predictions (the package's convention); each row is
normalised to per cent of its ground-truth points, so the diagonal is per-class recall.
"""

from __future__ import annotations

from html import escape

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.classes import CLASSES

_CELL = 46
_LEFT = 150
_TOP = 130


def _colour(fraction: float) -> str:
    # White -> deep blue, readable in print and for colour-blind readers.
    low = np.array([247, 251, 255])
    high = np.array([8, 48, 107])
    r, g, b = (low + (high - low) * min(max(fraction, 0.0), 1.0)).round().astype(int)
    return f"#{r:02x}{g:02x}{b:02x}"


def confusion_svg(confusion: NDArray[np.int64], *, title: str = "") -> str:
    """An SVG document showing ``confusion`` (n x n, rows ground truth) as a heatmap."""
    matrix = np.asarray(confusion, dtype=np.float64)
    n = matrix.shape[0]
    totals = matrix.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(totals > 0, matrix / totals, np.nan)
    names = [c.name for c in CLASSES][:n]
    width = _LEFT + n * _CELL + 10
    height = _TOP + n * _CELL + 40
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width} {height}" '
        f'width="{width}" height="{height}" role="img" font-family="sans-serif" font-size="11">',
        f"<title>{escape(title or 'Confusion matrix')}</title>",
        f'<text x="{_LEFT + n * _CELL / 2}" y="14" text-anchor="middle" font-weight="bold">'
        "prediction</text>",
        f'<text x="12" y="{_TOP + n * _CELL / 2}" text-anchor="middle" font-weight="bold" '
        f'transform="rotate(-90 12 {_TOP + n * _CELL / 2})">ground truth</text>',
    ]
    for j, name in enumerate(names):
        x = _LEFT + j * _CELL + _CELL / 2
        parts.append(
            f'<text x="{x}" y="{_TOP - 6}" transform="rotate(-45 {x} {_TOP - 6})">'
            f"{escape(name)}</text>"
        )
    for i, name in enumerate(names):
        y = _TOP + i * _CELL
        parts.append(
            f'<text x="{_LEFT - 6}" y="{y + _CELL / 2 + 4}" text-anchor="end">{escape(name)}</text>'
        )
        for j in range(n):
            value = share[i, j]
            x = _LEFT + j * _CELL
            fill = "#eeeeee" if np.isnan(value) else _colour(float(value))
            label = "–" if np.isnan(value) else f"{100 * value:.1f}"
            ink = "#ffffff" if not np.isnan(value) and value > 0.5 else "#222222"
            count = int(matrix[i, j])
            parts.append(
                f'<rect x="{x}" y="{y}" width="{_CELL}" height="{_CELL}" fill="{fill}" '
                f'stroke="#ffffff"><title>{escape(name)} → {escape(names[j])}: '
                f"{count} points</title></rect>"
                f'<text x="{x + _CELL / 2}" y="{y + _CELL / 2 + 4}" text-anchor="middle" '
                f'fill="{ink}">{label}</text>'
            )
    parts.append(
        f'<text x="{_LEFT}" y="{height - 12}">per cent of each ground-truth class (row); '
        "hover for point counts</text></svg>"
    )
    return "".join(parts)
