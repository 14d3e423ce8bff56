"""How the pages write numbers, counts and participants' text (the templates' filters).

Scores are fractions shown in per cent with one decimal (the paper prints three decimals
of a fraction: the same precision). Run times keep three significant figures in the
largest unit that leaves at most three digits before the point. Free text that
participants and administrators write (descriptions) is Markdown, rendered without raw
HTML and without unsafe links, so backticks and asterisks are never shown raw.
"""

from __future__ import annotations

from functools import cache

from markdown_it import MarkdownIt
from markupsafe import Markup


def format_percent(value: float | None) -> str:
    """A fraction in per cent with one decimal; ``–`` when unknown.

    >>> format_percent(0.6226), format_percent(0.0), format_percent(None)
    ('62.3', '0.0', '–')
    """
    return "–" if value is None else f"{100 * value:.1f}"


def format_seconds(value: float | None) -> str:
    """A run time for people: three significant figures, unit chosen by size.

    Seconds below 2 minutes, minutes below 2 hours, hours below 2 days, then days
    (milliseconds below 10 ms).

    >>> format_seconds(16.0136), format_seconds(0.5), format_seconds(563.6)
    ('16 s', '0.5 s', '9.39 min')
    >>> format_seconds(1800), format_seconds(38421), format_seconds(64800), format_seconds(1e7)
    ('30 min', '10.7 h', '18 h', '116 d')
    >>> format_seconds(0.0042), format_seconds(0), format_seconds(None)
    ('4.2 ms', '0 s', '–')
    """
    if value is None:
        return "–"
    if 0 < value < 0.01:
        return f"{value * 1000:.3g} ms"
    for limit, divisor, unit in ((120, 1, "s"), (7200, 60, "min"), (172_800, 3600, "h")):
        if value < limit:
            return f"{value / divisor:.3g} {unit}"
    return f"{value / 86_400:.3g} d"


def format_seconds_plain(value: float | None) -> str:
    """The run time in seconds, the unit of the paper's T column (a cell's tooltip):
    whole seconds with thousands separators from 1000 s, else four significant figures.

    >>> format_seconds_plain(64800), format_seconds_plain(563.6), format_seconds_plain(16.0136)
    ('64,800 s', '563.6 s', '16.01 s')
    >>> format_seconds_plain(None)
    'unknown'
    """
    if value is None:
        return "unknown"
    return f"{value:,.0f} s" if value >= 1000 else f"{value:.4g} s"


def plural(count: int | None, word: str, plural_word: str | None = None) -> str:
    """``count`` with ``word`` in the right number, thousands separated.

    >>> plural(1, "scan"), plural(15, "scan"), plural(1_000_000, "point"), plural(2, "entry", "entries")
    ('1 scan', '15 scans', '1,000,000 points', '2 entries')
    """
    n = count or 0
    return f"{n:,} {word if n == 1 else (plural_word or word + 's')}"


@cache
def _markdown() -> MarkdownIt:
    # CommonMark without raw HTML; markdown-it's link validation drops javascript:,
    # vbscript:, file: and data: (except images) links.
    return MarkdownIt("commonmark", {"html": False, "typographer": False}).disable("image")


def render_markdown(text: str | None) -> Markup:
    """``text`` as safe HTML: paragraphs, lists, emphasis, code and http(s) links."""
    if not text:
        return Markup("")
    return Markup(_markdown().render(text).replace("<a href=", '<a rel="nofollow noopener" href='))


def render_markdown_inline(text: str | None) -> Markup:
    """``text`` as safe inline HTML (no paragraphs): for one-line descriptions."""
    if not text:
        return Markup("")
    html = _markdown().renderInline(text)
    return Markup(html.replace("<a href=", '<a rel="nofollow noopener" href='))
