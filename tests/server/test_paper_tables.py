"""The boards hold Tables 1 and 2 of the semantic3D.net paper, cell by cell.

``golden/paper_tables.txt`` is the two tables as the paper's LaTeX source prints them; the
first test checks it against the source itself (when ``../shared/paper`` is there), the
second that the API, the CSV export and the page of each board carry every cell.
"""

from __future__ import annotations

import csv
import io
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

from semantic3d.core.classes import CLASSES
from semantic3d.server.services.leaderboard_export import iou_column
from tests.conftest import REPO_ROOT

from .board_html import MEAN_IOU, OVERALL_ACCURACY, RUNTIME, BoardTable
from .conftest import Harness

GOLDEN = Path(__file__).with_name("golden") / "paper_tables.txt"
PAPER_TEX = REPO_ROOT.parent / "shared" / "paper" / "semantic3d-net-2017.tex"
TABLE_LABELS = {"semantic-8": "tab:sem3d_full", "reduced-8": "tab:sem3d_reduced"}


@dataclass(frozen=True)
class PaperRow:
    """One row of the paper's tables, as printed: 12 cells after the method name."""

    challenge: str
    method: str
    cells: tuple[str, ...]  # mean IoU, OA, t [s], IoU_1..IoU_8

    def number(self, index: int) -> float | None:
        cell = self.cells[index].rstrip("*")
        return None if cell == "unknown" else float(cell)

    @property
    def mean_iou(self) -> float | None:
        return self.number(0)

    @property
    def overall_accuracy(self) -> float | None:
        return self.number(1)

    @property
    def runtime_s(self) -> float | None:
        return self.number(2)

    @property
    def iou(self) -> list[float | None]:
        return [self.number(3 + i) for i in range(len(CLASSES))]

    @property
    def marked(self) -> list[bool]:
        return [cell.endswith("*") for cell in self.cells[3:]]


def golden_rows() -> list[PaperRow]:
    rows = []
    for line in GOLDEN.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        challenge, method, *cells = (cell.strip() for cell in line.split("|"))
        rows.append(PaperRow(challenge, method, tuple(cells)))
    return rows


def _tex_rows(tex: str, challenge: str) -> list[PaperRow]:
    """The rows of the table labelled for ``challenge`` in the LaTeX source."""
    label = TABLE_LABELS[challenge]
    table = next(part for part in tex.split(r"\begin{table*}") if f"\\label{{{label}}}" in part)
    body = table.split(r"\hline", 1)[1].split(r"\end{tabular}")[0]
    rows = []
    for line in body.split(r"\\"):
        cells = [re.sub(r"\{\\bf\s*([^}]*)\}", r"\1", cell).strip() for cell in line.split("&")]
        if len(cells) == 1 + 3 + len(CLASSES):
            rows.append(PaperRow(challenge, cells[0], tuple(cells[1:])))
    return rows


def test_the_golden_tables_are_the_papers_tables() -> None:
    if not PAPER_TEX.is_file():
        pytest.skip("the paper's LaTeX source (../shared/paper) is not available")
    tex = PAPER_TEX.read_text()
    from_tex = [row for name in TABLE_LABELS for row in _tex_rows(tex, name)]
    assert from_tex == golden_rows()
    assert len(from_tex) == 4 + 3


def _close(a: float | None, b: float | None) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and abs(a - b) < 1e-12)


def test_the_boards_hold_the_papers_tables_cell_by_cell(harness: Harness) -> None:
    for challenge in TABLE_LABELS:
        expected = [row for row in golden_rows() if row.challenge == challenge]
        board = harness.client.get(f"/api/challenges/{challenge}/leaderboard").json()
        api = {row["method"]: row for row in board["references"]}
        text = harness.client.get(f"/challenges/{challenge}/leaderboard.csv").text
        exported = {row["method"]: row for row in csv.DictReader(io.StringIO(text))}
        page = {
            row.method: row
            for row in BoardTable.parse(harness.client.get(f"/challenges/{challenge}").text).rows
        }
        for paper in expected:
            row, line, html = api[paper.method], exported[paper.method], page[paper.method]
            assert row["tag"] in ("paper-baseline", "published"), paper.method
            assert "1704.03847" in row["source"]["url"] and row["source"]["year"] == 2017
            assert row["table"] == ("Table 1" if challenge == "semantic-8" else "Table 2")
            # The API, exactly.
            assert _close(row["mean_iou"], paper.mean_iou), paper.method
            assert _close(row["overall_accuracy"], paper.overall_accuracy), paper.method
            assert _close(row["runtime_s"], paper.runtime_s), paper.method
            for cls, value, marked in zip(CLASSES, paper.iou, paper.marked, strict=True):
                assert _close(row["iou"][str(cls.value)], value), (paper.method, cls.name)
                assert (str(cls.value) in row["iou_notes"]) is marked, (paper.method, cls.name)
            # The CSV, exactly.
            assert _close(float(line["mean_iou"]), paper.mean_iou)
            assert _close(float(line["overall_accuracy"]), paper.overall_accuracy)
            runtime = float(line["runtime_s"]) if line["runtime_s"] else None
            assert _close(runtime, paper.runtime_s)
            for cls, value in zip(CLASSES, paper.iou, strict=True):
                assert _close(float(line[iou_column(cls.name)]), value)
            # The page: full-precision values and the footnote marks.
            assert _close(html.number(MEAN_IOU), paper.mean_iou)
            assert _close(html.number(OVERALL_ACCURACY), paper.overall_accuracy)
            assert _close(html.number(RUNTIME), paper.runtime_s)
            assert all(_close(a, b) for a, b in zip(html.iou, paper.iou, strict=True))
            assert html.marked == paper.marked, paper.method
            assert html.cells[MEAN_IOU].text == f"{100 * paper.mean_iou:.1f}"
