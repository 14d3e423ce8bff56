"""Reports: JSON (NaN as null), Markdown tables, self-contained HTML."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest

from semantic3d.core.errors import DataFormatError
from semantic3d.evaluation import EvaluationResult, MethodInfo
from semantic3d.evaluation.report import (
    format_results_table,
    render_html,
    render_markdown,
    write_html,
    write_json,
    write_markdown,
)
from semantic3d.evaluation.result import ScanResult
from semantic3d.metrics import compute_scores


def _result(matrix: np.ndarray, method: MethodInfo | None) -> EvaluationResult:
    scores = compute_scores(matrix)
    return EvaluationResult(
        challenge="semantic-8",
        protocol_version="1",
        confusion=matrix,
        scores=scores,
        n_points=scores.n_points,
        method=method,
        per_scan=(ScanResult("scan", "scan.labels", matrix, scores),),
    )


@pytest.fixture
def result() -> EvaluationResult:
    matrix = np.diag([90, 80, 70, 40, 200, 30, 0, 10]).astype(np.int64)
    matrix[0, 1] = 10
    return _result(matrix, MethodInfo("Ours <b>", runtime_s=3600, hardware="1 CPU"))


def test_markdown_follows_the_paper_table(result: EvaluationResult) -> None:
    text = render_markdown(result)
    header = (
        "| Method | mIoU | OA | T | IoU 1 man-made terrain | IoU 2 natural terrain | "
        "IoU 3 high vegetation | IoU 4 low vegetation | IoU 5 buildings | IoU 6 hard scape | "
        "IoU 7 scanning artefacts | IoU 8 cars |"
    )
    assert header in text
    # IoU_1 = 90/100, IoU_2 = 80/90; mIoU over 7 present classes
    mean = (0.9 + 80 / 90 + 5) / 7
    row = f"| Ours <b> | {mean:.3f} | {520 / 530:.3f} | 3600 s | 0.900 | 0.889 | 1.000 |"
    assert row in text
    assert "| absent | 1.000 |" in text  # class 7 absent, class 8 perfect
    assert "left out of the mean: scanning artefacts." in text
    assert "## Confusion matrix (rows: ground truth, columns: prediction)" in text


def test_table_of_several_results_keeps_order(result: EvaluationResult) -> None:
    other = _result(result.confusion, None)
    lines = format_results_table([result, other]).splitlines()
    assert len(lines) == 4
    assert lines[2].startswith("| Ours <b> |") and lines[3].startswith("| (unnamed) |")
    assert "| – |" in lines[3]  # no runtime reported


def test_html_is_self_contained(result: EvaluationResult, tmp_path: Path) -> None:
    page = render_html(result)
    assert page.startswith("<!DOCTYPE html>")
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", page)  # no external assets
    assert "<link" not in page and "<script" not in page
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(images) == 2  # heatmap and IoU bars
    assert all(base64.b64decode(data).startswith(b"\x89PNG\r\n\x1a\n") for data in images)
    assert "Ours &lt;b&gt;" in page and "Ours <b>" not in page  # escaped
    write_html(tmp_path / "r.html", result)
    assert (tmp_path / "r.html").read_text() == page


def test_json_files(result: EvaluationResult, tmp_path: Path) -> None:
    write_json(tmp_path / "full.json", result)
    write_json(tmp_path / "public.json", result, include_per_scan=False)
    full = json.loads((tmp_path / "full.json").read_text())
    public = json.loads((tmp_path / "public.json").read_text())
    assert full["scores"]["iou"][6] is None and full["scores"]["precision"][6] is None
    assert full["per_scan"][0]["name"] == "scan"
    assert "per_scan" not in public
    assert full["method"]["runtime_s"] == 3600
    loaded = EvaluationResult.from_dict(full)
    assert loaded.to_dict() == result.to_dict()
    write_markdown(tmp_path / "r.md", result)
    assert (tmp_path / "r.md").read_text() == render_markdown(result)


def test_from_dict_rejects_other_formats(result: EvaluationResult) -> None:
    data = result.to_dict()
    data["format"] = "something-else/2"
    with pytest.raises(DataFormatError, match=r"expected format 'semantic3d\.evaluation-result/1'"):
        EvaluationResult.from_dict(data)
    data = result.to_dict()
    data["confusion"] = [[1, 2, 3]]
    with pytest.raises(DataFormatError, match="confusion: expected a square matrix"):
        EvaluationResult.from_dict(data)
