// Sortable leaderboard columns: click (or Enter/Space on) a heading with data-sort.
// A heading's data-column says which cell of a row it sorts by (headings grouped under
// a colspan have another index in their own header row). Numbers sort by each cell's
// data-value (empty cells last, whatever the direction); text by its content. A second
// click reverses the order. No dependencies.
"use strict";
(function () {
  function cellKey(row, index, kind) {
    // "position": the board's own order (ranks, with the unranked rows where they sort in).
    if (kind === "position") return Number(row.dataset.position);
    const cell = row.cells[index];
    if (!cell) return null;
    if (kind === "number") {
      const raw = cell.getAttribute("data-value");
      if (raw === null || raw === "") return null;
      const value = Number(raw);
      return Number.isFinite(value) ? value : null;
    }
    const text = cell.textContent.trim();
    return text === "" || text === "–" ? null : text.toLocaleLowerCase();
  }

  function sortBy(table, header) {
    const column = header.getAttribute("data-column");
    const index = column === null ? header.cellIndex : Number(column);
    const kind = header.getAttribute("data-sort");
    const current = header.getAttribute("aria-sort");
    // Numbers start high-to-low (scores), text and the rank column A-to-Z / 1-to-n.
    const startDescending = kind === "number";
    let descending = current ? current === "ascending" : startDescending;
    const body = table.tBodies[0];
    const rows = Array.from(body.rows);
    rows.sort(function (a, b) {
      const x = cellKey(a, index, kind);
      const y = cellKey(b, index, kind);
      if (x === null || y === null) {
        if (x === y) return Number(a.dataset.position) - Number(b.dataset.position);
        return x === null ? 1 : -1;
      }
      let order = 0;
      if (kind !== "text") order = x - y;
      else order = x.localeCompare(y);
      if (order === 0) return Number(a.dataset.position) - Number(b.dataset.position);
      return descending ? -order : order;
    });
    rows.forEach(function (row) { body.appendChild(row); });
    table.querySelectorAll("th[data-sort]").forEach(function (th) {
      th.removeAttribute("aria-sort");
    });
    header.setAttribute("aria-sort", descending ? "descending" : "ascending");
  }

  document.querySelectorAll("table.sortable").forEach(function (table) {
    table.querySelectorAll("th[data-sort]").forEach(function (header) {
      header.tabIndex = 0;
      header.title = (header.title ? header.title + " · " : "") + "sort by this column";
      header.addEventListener("click", function () { sortBy(table, header); });
      header.addEventListener("keydown", function (event) {
        if (event.key === "Enter" || event.key === " ") {
          event.preventDefault();
          sortBy(table, header);
        }
      });
    });
  });
})();
