// The labelling page: panels, selection tools, model fits, layers, undo/redo, save, measure.
import { api } from '/static/api.js';
import { SelectionTool, describeMeasures } from '/static/tools.js';
import { RAMP, Viewer } from '/static/viewer.js';

const $ = (id) => document.getElementById(id);
const EDIT_KEYS = new Set(['d', 'l', 'b', 'p', 'w', 'backspace', 'enter']);

// Every key the page knows (the help panel lists this table; the viewer only the rows that
// do not edit). Each row: the keys as the help shows them, what they do, whether they edit.
const KEYS = [
  ['Ctrl+Z', 'undo', true],
  ['Ctrl+Y, Ctrl+Shift+Z', 'redo', true],
  ['Ctrl+S', 'save', true],
  ['D', 'draw a polygon (click the vertices)', true],
  ['L', 'lasso (drag around the points)', true],
  ['B', 'brush (paint over the points)', true],
  ['Enter, double-click', 'close the polygon', true],
  ['Backspace', 'remove the polygon\'s last vertex', true],
  ['Escape', 'cancel the selection, the picks or the measure; close this help', false],
  ['P', 'pick points for a model fit', true],
  ['M', 'measure: coordinates, distances, heights', false],
  ['O', 'orbit view', false],
  ['T', 'top view', false],
  ['F', 'front view', false],
  ['S', 'side view', false],
  ['V', '2D view along the current direction', false],
  ['W', 'frame the working set', true],
  ['+, =, -', 'bigger (+ or =), smaller (-) points', false],
  ['H, ?', 'this help', false],
];

function storageKey(scan) { return `semantic3d:view:${scan.name}:${scan.hierarchy.n_points}`; }

class LabelApp {
  constructor(scan) {
    this.scan = scan;
    this.summary = scan.summary;
    this.picks = [];
    this.measures = [];
    this.mode = 'orbit';
    this.preview = null;
    this.busy = false;
    this.queue = Promise.resolve();
    this.viewer = new Viewer($('stage'), scan);
    this.tool = new SelectionTool(this);
    this.viewer.onChange(() => { this.showStatus(); this.showScale(); });
    this.readOnly = scan.summary.read_only;
    document.body.classList.toggle('read-only', this.readOnly);
    $('scan-name').textContent = scan.name;
    const s = scan.summary;
    if (this.readOnly) { // the viewer's working set is the whole scan
      $('stats-working').textContent = 'count scan';
      $('stats-working').title = 'counts (and confusion) of the whole scan';
    }
    $('mode-line').textContent = this.readOnly ? 'read-only viewer'
      : `labelling → ${s.labels_path}` + (s.started_from ? ` (started from ${s.started_from})` : '');
    if (!s.has_prediction) {
      for (const v of ['prediction', 'errors']) $('colour-mode').querySelector(`[value=${v}]`).disabled = true;
    }
    for (const select of [$('assign-class'), $('move-source'), $('move-target')]) {
      for (const c of scan.classes) select.add(new Option(`${c.value} ${c.name}`, c.value));
    }
    $('assign-class').value = '1';
    $('help-keys').innerHTML = KEYS.filter(([, , edits]) => !(edits && this.readOnly))
      .map(([k, what]) => `<tr><td>${k}</td><td>${what}</td></tr>`).join('');
    this.bind();
    this.restoreSettings();
    this.showSummary(s);
    this.showLegend();
    this.viewer.requestRender(true);
  }

  // --- settings remembered across reloads ------------------------------------------------------

  restoreSettings() {
    let saved = null;
    try { saved = JSON.parse(localStorage.getItem(storageKey(this.scan)) || 'null'); } catch { saved = null; }
    const v = this.viewer;
    if (saved) {
      if (saved.colourMode && !$('colour-mode').querySelector(`[value=${saved.colourMode}]`).disabled) {
        $('colour-mode').value = saved.colourMode; v.colourMode = saved.colourMode;
      }
      if (saved.budget) { $('point-budget').value = String(saved.budget); v.setBudget(Number(saved.budget)); }
      if (saved.pointSize) { $('point-size').value = String(saved.pointSize); v.setPointSize(Number(saved.pointSize)); }
      this.restoredView = v.restoreView(saved.view);
    } else {
      v.setBudget(Number($('point-budget').value));
    }
    // The start view frames the dense part of the scan (far returns inflate its bounds).
    v.onDenseFrame = () => { if (!this.restoredView) v.frameBox(v.frame); this.showLegend(); };
    this.markView();
    window.addEventListener('beforeunload', () => this.saveSettings());
    this.viewer.onChange(() => { clearTimeout(this.saveTimer); this.saveTimer = setTimeout(() => this.saveSettings(), 400); });
  }

  saveSettings() {
    const v = this.viewer;
    const settings = { view: v.viewState(), colourMode: v.colourMode, budget: v.pointBudget, pointSize: v.pointSize };
    try { localStorage.setItem(storageKey(this.scan), JSON.stringify(settings)); } catch { /* storage full or off */ }
  }

  bind() {
    const v = this.viewer;
    $('colour-mode').onchange = (e) => { v.colourMode = e.target.value; v.recolour(); this.showLegend(); this.saveSettings(); };
    $('point-size').oninput = (e) => v.setPointSize(Number(e.target.value));
    $('point-budget').onchange = (e) => { v.setBudget(Number(e.target.value)); this.saveSettings(); };
    $('dim-outside').onchange = (e) => { v.dimOutside = e.target.checked; v.recolour(); };
    for (const view of ['free', 'top', 'front', 'side', 'free2d']) $(`view-${view}`).onclick = () => this.setView(view);
    $('frame-working').onclick = () => v.frameWorking();
    $('frame-dense').onclick = () => v.frameBox(v.frame);
    $('range-low').onchange = () => this.setRange();
    $('range-high').onchange = () => this.setRange();
    $('range-auto').onclick = () => { v.setRange(this.rangeKind(), null); this.showLegend(); };
    $('help-toggle').onclick = () => this.toggleHelp();
    // selection in a fixed view
    for (const kind of ['polygon', 'lasso', 'brush']) $(`draw-${kind}`).onclick = () => this.startSelection(kind);
    $('finish-polygon').onclick = () => this.tool.close();
    $('cancel-polygon').onclick = () => this.tool.cancel();
    $('keep-inside').onclick = () => this.applySelection('inside');
    $('keep-outside').onclick = () => this.applySelection('outside');
    // 3D workflow
    $('pick-points').onclick = () => this.setMode(this.mode === 'pick' ? 'orbit' : 'pick');
    $('clear-picks').onclick = () => this.clearPicks();
    $('tolerance').oninput = (e) => { $('tolerance-value').value = Number(e.target.value).toFixed(2); };
    $('tolerance').onchange = () => this.refreshPreview();
    $('tolerance-value').onchange = (e) => { $('tolerance').value = e.target.value; this.refreshPreview(); };
    $('region-kind').onchange = () => this.refreshPreview();
    $('region-size').onchange = () => { this.regionSizeSet = true; this.refreshPreview(); };
    $('model-kind').onchange = () => this.refreshPreview();
    $('fit-preview').onclick = () => this.fitPreview();
    $('fit-model').onclick = () => this.fit();
    // measure
    $('measure').onclick = () => this.setMode(this.mode === 'measure' ? 'orbit' : 'measure');
    $('clear-measure').onclick = () => this.clearMeasures();
    v.renderer.domElement.addEventListener('click', (e) => this.clickScene(e));
    // layers, counts and history
    $('assign').onclick = () => this.run('/api/assign', { value: Number($('assign-class').value) }, true);
    $('reset-all').onclick = () => this.run('/api/reset', { scope: 'all' });
    $('reset-unlabelled').onclick = () => this.run('/api/reset', { scope: 'unlabelled' });
    $('move-layer').onclick = () => this.run('/api/move-layer', {
      source: Number($('move-source').value), target: Number($('move-target').value),
    });
    $('undo').onclick = () => this.run('/api/undo', {});
    $('redo').onclick = () => this.run('/api/redo', {});
    $('save').onclick = () => this.save();
    $('stats-working').onclick = () => this.showStats('working');
    $('stats-view').onclick = () => this.showStats('view');
    $('cancel-operation').onclick = () => api('/api/cancel', {}).catch(() => null);
    document.addEventListener('keydown', (e) => this.key(e));
    // A choice made in a list hands the keyboard back to the page (T, F, S... work at once).
    for (const select of document.querySelectorAll('select')) select.addEventListener('change', () => select.blur());
  }

  key(e) {
    const tag = e.target.tagName;
    if ((tag === 'INPUT' && e.target.type !== 'range' && e.target.type !== 'checkbox') || tag === 'SELECT') return;
    const key = e.key.toLowerCase();
    const ctrl = e.ctrlKey || e.metaKey;
    if (this.readOnly && (ctrl || EDIT_KEYS.has(key))) return;
    if (ctrl && key === 'z') { e.preventDefault(); this.run(e.shiftKey ? '/api/redo' : '/api/undo', {}); }
    else if (ctrl && key === 'y') { e.preventDefault(); this.run('/api/redo', {}); }
    else if (ctrl && key === 's') { e.preventDefault(); this.save(); }
    else if (ctrl || e.altKey) return;
    else if (key === 'enter' && this.tool.kind === 'polygon') this.tool.close();
    else if (key === 'backspace') { if (this.tool.removeVertex()) e.preventDefault(); }
    else if (key === 'escape') { this.tool.cancel(); this.setMode('orbit'); $('help').hidden = true; }
    else if (key === 'd') this.startSelection('polygon');
    else if (key === 'l') this.startSelection('lasso');
    else if (key === 'b') this.startSelection('brush');
    else if (key === 'p') this.setMode(this.mode === 'pick' ? 'orbit' : 'pick');
    else if (key === 'm') this.setMode(this.mode === 'measure' ? 'orbit' : 'measure');
    else if (key === 'o') this.setView('free');
    else if (key === 't') this.setView('top');
    else if (key === 'f') this.setView('front');
    else if (key === 's') this.setView('side');
    else if (key === 'v') this.setView('free2d');
    else if (key === 'w') this.viewer.frameWorking();
    else if (key === '+' || key === '=') this.bumpPointSize(0.5);
    else if (key === '-') this.bumpPointSize(-0.5);
    else if (key === 'h' || key === '?') this.toggleHelp();
  }

  toggleHelp() { $('help').hidden = !$('help').hidden; }

  bumpPointSize(step) {
    const size = Math.min(8, Math.max(1, this.viewer.pointSize + step));
    $('point-size').value = String(size);
    this.viewer.setPointSize(size);
  }

  setView(view) {
    this.tool.cancel();
    this.viewer.setView(view);
    this.markView();
    this.saveSettings();
  }

  markView() {
    for (const view of ['free', 'top', 'front', 'side', 'free2d']) $(`view-${view}`).classList.toggle('active', this.viewer.view === view);
    this.showScale();
  }

  setMode(mode) {
    this.mode = mode;
    $('pick-points').classList.toggle('active', mode === 'pick');
    $('measure').classList.toggle('active', mode === 'measure');
  }

  // --- legend, colour ranges, scale bar and axes ------------------------------------------------

  rangeKind() { return this.viewer.colourMode === 'height' ? 'height' : 'intensity'; }

  setRange() {
    const low = Number($('range-low').value), high = Number($('range-high').value);
    if (!(high > low)) { this.showError('colour range: expected from < to'); return; }
    const kind = this.rangeKind();
    const shift = kind === 'height' ? this.scan.hierarchy.origin[2] : 0;
    this.viewer.setRange(kind, [low - shift, high - shift]);
    this.showLegend();
  }

  showLegend() {
    const v = this.viewer, mode = v.colourMode, legend = $('legend');
    const swatch = (colour, name) => `<span class="item"><span class="swatch" style="background:${colour}"></span> ${name}</span>`;
    const rgb = (c) => `rgb(${c.map(Math.round).join(',')})`;
    $('range-controls').hidden = !(mode === 'height' || mode === 'intensity');
    if (mode === 'class' || mode === 'prediction') {
      legend.innerHTML = this.scan.classes.map((c) => swatch(c.colour, `${c.value} ${c.name}`)).join('')
        + (mode === 'prediction' ? swatch('rgb(90,90,90)', 'no prediction') : '');
    } else if (mode === 'errors') {
      legend.innerHTML = swatch('rgb(40,180,60)', 'right') + swatch('rgb(230,30,30)', 'wrong')
        + swatch('rgb(90,90,90)', 'unlabelled truth or no prediction');
    } else if (mode === 'rgb') {
      legend.innerHTML = '<span class="item">colours as scanned</span>';
    } else {
      const kind = this.rangeKind();
      const shift = kind === 'height' ? this.scan.hierarchy.origin[2] : 0;
      const [low, high] = v.ranges[kind].map((x) => x + shift);
      const stops = kind === 'height' ? RAMP.map(rgb).join(',') : 'black,white';
      const unit = kind === 'height' ? ' m' : ' (0–255 of the scan\'s range)';
      legend.innerHTML = `<div class="ramp" style="background:linear-gradient(to right,${stops})"></div>`
        + `<div class="ends"><span>${low.toFixed(2)}</span><span>${kind}${unit}</span><span>${high.toFixed(2)}</span></div>`;
      $('range-low').value = low.toFixed(2);
      $('range-high').value = high.toFixed(2);
    }
  }

  showScale() {
    const v = this.viewer;
    const shown = v.is2d;
    $('scale-bar').hidden = !shown;
    $('axes').hidden = !shown;
    if (!shown) return;
    const mpp = v.metresPerPixel();
    const target = 120 * mpp, power = 10 ** Math.floor(Math.log10(target));
    const length = [1, 2, 5, 10].map((m) => m * power).filter((l) => l <= target).pop() || power;
    $('scale-line').style.width = `${length / mpp}px`;
    $('scale-text').textContent = length >= 1 ? `${length} m` : `${Math.round(length * 1000)} mm`;
    const name = (vec) => {
      const axis = vec.map(Math.abs).indexOf(Math.max(...vec.map(Math.abs)));
      if (Math.abs(vec[axis]) > 0.999) return `${vec[axis] > 0 ? '+' : '−'}${'xyz'[axis]}`;
      return `(${vec.map((c) => c.toFixed(2)).join(', ')})`;
    };
    const { right, up } = v.screenAxes();
    $('axes').textContent = `→ ${name(right)}\n↑ ${name(up)}`;
  }

  // --- selection in a fixed view ---------------------------------------------------------------

  startSelection(kind) {
    if (this.readOnly) return;
    this.setMode('orbit');
    this.tool.start(kind);
  }

  async applySelection(keep) {
    if (!this.tool.ready) return;
    const [path, body] = this.tool.request(keep);
    await this.run(path, body);
  }

  // --- picks, fits and measures ------------------------------------------------------------------

  clickScene(e) {
    if (this.mode !== 'pick' && this.mode !== 'measure') return;
    const point = this.viewer.pick(e.clientX, e.clientY);
    if (!point) { this.showError('no point under the cursor'); return; }
    this.showError('');
    if (this.mode === 'pick') { this.picks.push(point); this.showPicks(); this.refreshPreview(); }
    else { this.measures.push(point); this.showMeasures(); }
  }

  clearPicks() { this.picks = []; this.clearPreview(); this.showPicks(); }

  showPicks() {
    $('pick-count').textContent = `${this.picks.length} picked`;
    this.viewer.showPicks(this.picks);
    if (!this.regionSizeSet && this.picks.length) {
      const centre = this.picksCentre();
      const spread = Math.max(...this.picks.map((p) => Math.hypot(p[0] - centre[0], p[1] - centre[1], p[2] - centre[2])));
      $('region-size').value = String(Math.max(2, Math.round(3 * spread)));
    }
  }

  picksCentre() { return [0, 1, 2].map((k) => this.picks.reduce((s, p) => s + p[k], 0) / this.picks.length); }

  clearMeasures() { this.measures = []; this.showMeasures(); }

  showMeasures() {
    $('measure-result').textContent = describeMeasures(this.measures, this.scan.hierarchy.origin);
    this.viewer.showMeasure(this.measures);
  }

  fitBody() {
    const body = { kind: $('model-kind').value, seeds: this.picks, tolerance_m: Number($('tolerance-value').value) };
    const kind = $('region-kind').value, size = Number($('region-size').value);
    const centre = this.picksCentre();
    if (kind === 'sphere') body.region = { kind, centre, radius_m: size };
    else if (kind === 'box') body.region = { kind, min: centre.map((c) => c - size), max: centre.map((c) => c + size) };
    return body;
  }

  async fitPreview() {
    if (!this.picks.length) { this.showError('pick points on the surface first'); return; }
    const body = this.fitBody();
    this.viewer.showRegion(body.region || null);
    const data = await this.run('/api/fit/preview', body, false, false);
    if (!data) return;
    this.preview = { body: JSON.stringify(body), model: data.model };
    this.viewer.showPreview(data.sample);
    const rms = data.rms_m === null ? '–' : `${(data.rms_m * 1000).toFixed(1)} mm`;
    $('fit-result').textContent = `preview: ${data.model.kind}, ${data.n_inliers.toLocaleString()} inliers, rms ${rms}`;
  }

  refreshPreview() {
    if (this.preview && this.picks.length) { clearTimeout(this.previewTimer); this.previewTimer = setTimeout(() => this.fitPreview(), 150); }
  }

  clearPreview() {
    this.preview = null;
    this.viewer.showPreview([]);
    this.viewer.showRegion(null);
  }

  async fit() {
    if (!this.picks.length) { this.showError('pick points on the surface first'); return; }
    const body = this.fitBody();
    if (this.preview && this.preview.body === JSON.stringify(body)) body.model = this.preview.model;
    const data = await this.run('/api/fit', body);
    if (data) {
      const r = data.result;
      const rms = r.rms_m === null ? '–' : `${(r.rms_m * 1000).toFixed(1)} mm`;
      $('fit-result').textContent = `${r.model.kind}: ${r.n_inliers.toLocaleString()} inliers, rms ${rms}`;
      this.clearPreview();
    }
  }

  // --- operations ----------------------------------------------------------------------------

  // Operations run one after the other, in the order they were asked for.
  run(path, body, clearPicks = false, refresh = true) {
    const next = this.queue.then(() => this.runNow(path, body, clearPicks, refresh));
    this.queue = next.catch(() => null);
    return next;
  }

  async runNow(path, body, clearPicks, refresh) {
    this.busy = true;
    this.showStatus();
    const watch = setTimeout(() => this.watchProgress(), 300);
    try {
      const data = await this.call(path, body);
      if (clearPicks) this.clearPicks();
      this.showError('');
      if (refresh) {
        await this.viewer.refreshStates();
        this.showSummary(data.summary);
      }
      return data;
    } catch (error) {
      this.showError(error.message);
      return null;
    } finally {
      clearTimeout(watch);
      this.busy = false;
      $('progress').hidden = true;
      this.showStatus();
    }
  }

  // Progress of a long operation, polled until it ends; it can be cancelled meanwhile.
  async watchProgress() {
    while (this.busy) {
      try {
        const p = await api('/api/progress');
        if (!this.busy) break;
        $('progress').hidden = false;
        $('progress-bar').value = p.total ? p.done / p.total : 0;
        $('progress-text').textContent = p.running ? `${p.operation}: ${Math.round((100 * p.done) / Math.max(p.total, 1))} %` : '';
        $('cancel-operation').disabled = !p.cancellable;
      } catch { /* the next poll will tell */ }
      await new Promise((resolve) => setTimeout(resolve, 250));
    }
  }

  // An assignment of the whole scan asks first (the server refuses it unconfirmed).
  async call(path, body) {
    try {
      return await api(path, body);
    } catch (error) {
      if (error.status === 409 && error.data && error.data.confirm && path === '/api/assign') {
        if (!window.confirm(`${error.message}?`)) throw new Error('assignment cancelled');
        return api(path, { ...body, confirm_whole_scan: true });
      }
      throw error;
    }
  }

  async save() {
    await this.queue;
    try {
      const data = await api('/api/save', {});
      $('save-status').textContent = `saved ${data.path}`;
      this.showError('');
    } catch (error) {
      this.showError(error.message);
    }
  }

  async showStats(scope) {
    const body = scope === 'view' ? { scope, view_projection: this.viewer.viewProjection() } : { scope };
    const data = await this.run('/api/stats', body, false, false);
    if (!data) return;
    const classes = this.scan.classes;
    const pct = (x) => (x === null ? '–' : (100 * x).toFixed(1));
    const where = scope === 'view' ? 'in view' : this.readOnly ? 'scan' : 'working set';
    let html = `<table><caption>${where}: ${data.n_points.toLocaleString()} points</caption>`
      + '<tr><th>class</th><th>points</th>' + (data.has_prediction ? '<th>predicted</th><th>prec.</th><th>recall</th><th>IoU</th>' : '') + '</tr>';
    classes.forEach((c, value) => {
      html += `<tr><td><span class="swatch" style="background:${c.colour}"></span> ${c.name}</td><td>${data.counts[value].toLocaleString()}</td>`;
      if (data.has_prediction) {
        html += `<td>${data.prediction_counts[value].toLocaleString()}</td>`;
        html += value === 0 ? '<td></td><td></td><td></td>' : `<td>${pct(data.precision[value - 1])}</td><td>${pct(data.recall[value - 1])}</td><td>${pct(data.iou[value - 1])}</td>`;
      }
      html += '</tr>';
    });
    html += '</table>';
    if (data.has_prediction) {
      html += '<table class="confusion"><caption>confusion: rows truth, columns prediction</caption><tr><th></th>'
        + classes.slice(1).map((c) => `<th title="${c.name}">${c.value}</th>`).join('') + '</tr>';
      data.confusion.forEach((row, i) => {
        html += `<tr><th title="${classes[i + 1].name}">${i + 1}</th>` + row.map((n) => `<td>${n}</td>`).join('') + '</tr>';
      });
      html += `</table><p class="muted">overall accuracy ${pct(data.overall_accuracy)} %</p>`;
    }
    $('stats').innerHTML = html;
  }

  showError(message) { $('error').textContent = message; }

  showSummary(summary) {
    this.summary = summary;
    $('working-count').textContent = summary.n_working.toLocaleString();
    $('undo').disabled = !summary.can_undo;
    $('redo').disabled = !summary.can_redo;
    const body = $('layers').querySelector('tbody');
    body.innerHTML = '';
    for (const layer of summary.layers) {
      const c = this.scan.classes[layer.value];
      const row = body.insertRow();
      row.dataset.value = layer.value;
      row.insertCell().innerHTML = `<span class="swatch" style="background:${c.colour}"></span>`;
      row.insertCell().textContent = c.name;
      const count = row.insertCell();
      count.className = 'count';
      count.textContent = layer.count.toLocaleString();
      const show = document.createElement('input');
      show.type = 'checkbox'; show.checked = !layer.hidden; show.className = 'show-layer';
      show.onchange = () => this.setLayer(layer.value, { hidden: !show.checked });
      row.insertCell().appendChild(show);
      const lockCell = row.insertCell();
      lockCell.className = 'edit';
      const lock = document.createElement('input');
      lock.type = 'checkbox'; lock.checked = layer.locked; lock.className = 'lock-layer';
      lock.onchange = () => this.setLayer(layer.value, { locked: lock.checked });
      lockCell.appendChild(lock);
      this.viewer.hidden[layer.value] = layer.hidden;
    }
  }

  async setLayer(value, change) {
    if (this.readOnly) {
      if (change.hidden !== undefined) { this.viewer.hidden[value] = change.hidden; this.viewer.recolour(); }
      return;
    }
    try {
      const data = await api(`/api/layers/${value}`, change);
      this.showSummary(data.summary);
      this.viewer.recolour();
    } catch (error) { this.showError(error.message); }
  }

  showStatus() {
    const s = this.viewer.stats();
    $('status').textContent = `${s.points.toLocaleString()} points in ${s.nodes} nodes shown` +
      (s.inFlight ? ` · loading ${s.inFlight}` : ' · idle') + (this.busy ? ' · working…' : '');
    $('status').dataset.idle = String(!s.inFlight && !this.busy && !s.moving);
  }
}

async function main() {
  try {
    const scan = await api('/api/scan');
    window.labelApp = new LabelApp(scan);
  } catch (error) {
    $('error').textContent = `could not open the scan: ${error.message}`;
  }
}

main();
