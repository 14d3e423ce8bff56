"""Reading a leaderboard page back: the rows of its ``#leaderboard`` table, cell by cell."""

from __future__ import annotations

from dataclasses import dataclass, field
from html.parser import HTMLParser

from semantic3d.core.classes import CLASSES

# Cell positions in a body row (the headings' data-column values).
RANK, METHOD, TAG, MEAN_IOU, OVERALL_ACCURACY = 0, 1, 2, 3, 4
FIRST_IOU = 5
RUNTIME = FIRST_IOU + len(CLASSES)


@dataclass
class Cell:
    """One ``td``: its ``data-value`` (None without one), text and tooltip."""

    value: str | None
    text: str = ""
    title: str | None = None


@dataclass
class Row:
    """One body row: its tag, the method link and its cells."""

    tag: str | None
    href: str | None = None
    cells: list[Cell] = field(default_factory=list)

    @property
    def method(self) -> str:
        return self.cells[METHOD].text.split("\n")[0].strip()

    def number(self, index: int) -> float | None:
        """The full-precision value of cell ``index`` (None when empty)."""
        value = self.cells[index].value
        return None if value in (None, "") else float(value)

    @property
    def iou(self) -> list[float | None]:
        return [self.number(FIRST_IOU + i) for i in range(len(CLASSES))]

    @property
    def marked(self) -> list[bool]:
        """Per class: whether the cell carries a footnote mark."""
        return [self.cells[FIRST_IOU + i].text.endswith("*") for i in range(len(CLASSES))]


class BoardTable(HTMLParser):
    """The ``#leaderboard`` table: headings (``data-sort``, ``data-column``) and rows."""

    def __init__(self) -> None:
        super().__init__()
        self.headings: list[dict[str, str | None]] = []
        self.rows: list[Row] = []
        self._in_table = self._in_body = False
        self._cell: Cell | None = None
        self._first_link: bool = False

    @classmethod
    def parse(cls, html: str) -> BoardTable:
        table = cls()
        table.feed(html)
        return table

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = dict(attrs)
        if tag == "table" and values.get("id") == "leaderboard":
            self._in_table = True
        if not self._in_table:
            return
        if tag == "th":
            self.headings.append(values)
        elif tag == "tbody":
            self._in_body = True
        elif tag == "tr" and self._in_body:
            self.rows.append(Row(tag=values.get("data-tag")))
        elif tag == "td" and self._in_body:
            self._cell = Cell(values.get("data-value"), title=values.get("title"))
            self.rows[-1].cells.append(self._cell)
        elif tag == "a" and self._cell is not None and "method" in (values.get("class") or ""):
            self.rows[-1].href = values.get("href")
        elif tag == "br" and self._cell is not None:
            self._cell.text += "\n"

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self._in_table = self._in_body = False
        elif tag == "td":
            if self._cell is not None:
                self._cell.text = self._cell.text.strip()
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.text += data
