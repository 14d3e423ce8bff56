"""How the pages write run times, counts, scores and participants' Markdown."""

from __future__ import annotations

import pytest

from semantic3d.server.formatting import (
    format_percent,
    format_seconds,
    format_seconds_plain,
    plural,
    render_markdown,
    render_markdown_inline,
)


@pytest.mark.parametrize(
    ("seconds", "shown"),
    [
        (None, "–"),
        (0, "0 s"),
        (0.0042, "4.2 ms"),
        (0.5, "0.5 s"),
        (16.0136, "16 s"),
        (119.4, "119 s"),
        (563.6, "9.39 min"),
        (600, "10 min"),
        (1800, "30 min"),
        (5400, "90 min"),
        (38_421, "10.7 h"),
        (64_800, "18 h"),
        (1e7, "116 d"),
    ],
)
def test_run_times_have_three_significant_figures_at_most(
    seconds: float | None, shown: str
) -> None:
    assert format_seconds(seconds) == shown
    number = shown.split()[0].replace(".", "")
    assert shown == "–" or len(number.lstrip("0")) <= 3


def test_the_tooltip_gives_seconds_and_counts_agree_in_number() -> None:
    assert format_seconds_plain(64_800) == "64,800 s"
    assert format_seconds_plain(563.6) == "563.6 s"
    assert format_seconds_plain(16.0136) == "16.01 s"
    assert format_seconds_plain(None) == "unknown"
    assert plural(1, "scan") == "1 scan" and plural(4, "scan") == "4 scans"
    assert plural(0, "scan") == "0 scans" and plural(None, "point") == "0 points"
    assert plural(78_699_329, "point") == "78,699,329 points"
    assert format_percent(0.6226) == "62.3" and format_percent(None) == "–"


def test_markdown_is_rendered_without_raw_html_or_unsafe_links() -> None:
    text = (
        "Run `semantic3d demo`, **fast**. <script>alert(1)</script> "
        "<img src=x onerror=alert(1)> [bad](javascript:alert(1)) [ok](https://example.org)"
    )
    html = str(render_markdown(text))
    assert "<code>semantic3d demo</code>" in html and "<strong>fast</strong>" in html
    assert "<script" not in html and "<img" not in html and "&lt;script&gt;" in html
    assert 'href="javascript' not in html
    assert '<a rel="nofollow noopener" href="https://example.org">ok</a>' in html
    inline = str(render_markdown_inline("The held-out station of `semantic3d demo`."))
    assert inline == "The held-out station of <code>semantic3d demo</code>."
    assert str(render_markdown("")) == "" and str(render_markdown_inline(None)) == ""
    assert "<img" not in str(render_markdown("![x](https://example.org/a.png)"))
