// Leaderboard tag filter: the checkboxes of #tag-filter show or hide the rows of each tag
// (tr[data-tag]). The fieldset stays hidden without JavaScript, where every row shows.
// No dependencies.
"use strict";
(function () {
  const filter = document.getElementById("tag-filter");
  const table = document.getElementById("leaderboard");
  if (!filter || !table) return;
  const boxes = Array.from(filter.querySelectorAll("input[type=checkbox]"));
  const count = document.getElementById("shown-count");

  function apply() {
    const shown = new Set(boxes.filter(function (box) { return box.checked; })
      .map(function (box) { return box.value; }));
    let visible = 0;
    Array.from(table.tBodies[0].rows).forEach(function (row) {
      const show = shown.has(row.getAttribute("data-tag"));
      row.hidden = !show;
      if (show) visible += 1;
    });
    if (count) count.textContent = visible + (visible === 1 ? " row" : " rows");
  }

  boxes.forEach(function (box) { box.addEventListener("change", apply); });
  filter.hidden = false;
  apply();
})();
