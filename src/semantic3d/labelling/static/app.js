// The labelling page: panels, the 2D polygon and 3D fitting workflows, layers, undo/redo, save.
import { api } from '/static/api.js';
import { Viewer } from '/static/viewer.js';

const $ = (id) => document.getElementById(id);

class LabelApp {
  constructor(scan) {
    this.scan = scan;
    this.summary = scan.summary;
    this.picks = [];
    this.polygon = [];
    this.mode = 'orbit';
    this.lastFit = null;
    this.busy = false;
    this.queue = Promise.resolve();
    this.viewer = new Viewer($('stage'), scan);
    this.viewer.onChange(() => this.showStatus());
    document.body.classList.toggle('read-only', scan.summary.read_only);
    $('scan-name').textContent = scan.name;
    $('mode-line').textContent = scan.summary.read_only
      ? 'read-only viewer' : `labelling → ${scan.summary.labels_path}`;
    if (!scan.summary.has_prediction) {
      for (const v of ['prediction', 'errors']) $('colour-mode').querySelector(`[value=${v}]`).disabled = true;
    }
    for (const select of [$('assign-class'), $('move-source'), $('move-target')]) {
      for (const c of scan.classes) select.add(new Option(`${c.value} ${c.name}`, c.value));
    }
    $('assign-class').value = '1';
    this.bind();
    this.showSummary(scan.summary);
    this.viewer.requestRender(true);
  }

  bind() {
    const v = this.viewer;
    $('colour-mode').onchange = (e) => { v.colourMode = e.target.value; v.recolour(); };
    $('point-size').oninput = (e) => v.setPointSize(Number(e.target.value));
    $('point-budget').onchange = (e) => v.setBudget(Number(e.target.value));
    $('dim-outside').onchange = (e) => { v.dimOutside = e.target.checked; v.recolour(); };
    for (const view of ['free', 'top', 'front', 'side']) {
      $(`view-${view}`).onclick = () => { this.cancelPolygon(); v.setView(view); this.markView(); };
    }
    this.markView();
    $('frame-working').onclick = () => v.frameWorking();
    // 2D workflow
    $('draw-polygon').onclick = () => this.startPolygon();
    $('finish-polygon').onclick = () => this.finishPolygon();
    $('cancel-polygon').onclick = () => this.cancelPolygon();
    $('keep-inside').onclick = () => this.split('inside');
    $('keep-outside').onclick = () => this.split('outside');
    const overlay = $('overlay');
    overlay.addEventListener('click', (e) => this.addVertex(e));
    overlay.addEventListener('dblclick', (e) => { e.preventDefault(); this.finishPolygon(); });
    // 3D workflow
    $('pick-points').onclick = () => this.setMode(this.mode === 'pick' ? 'orbit' : 'pick');
    $('clear-picks').onclick = () => this.clearPicks();
    $('tolerance').oninput = (e) => { $('tolerance-value').textContent = `${Number(e.target.value).toFixed(2)} m`; };
    $('tolerance').onchange = () => { if (this.lastFit !== null) this.fit(true); };
    $('fit-model').onclick = () => this.fit(false);
    v.renderer.domElement.addEventListener('click', (e) => this.pickAt(e));
    // layers and history
    $('assign').onclick = () => this.run('/api/assign', { value: Number($('assign-class').value) }, true);
    $('reset-all').onclick = () => this.run('/api/reset', { scope: 'all' });
    $('reset-unlabelled').onclick = () => this.run('/api/reset', { scope: 'unlabelled' });
    $('move-layer').onclick = () => this.run('/api/move-layer', {
      source: Number($('move-source').value), target: Number($('move-target').value),
    });
    $('undo').onclick = () => this.run('/api/undo', {});
    $('redo').onclick = () => this.run('/api/redo', {});
    $('save').onclick = () => this.save();
    document.addEventListener('keydown', (e) => {
      if (this.summary.read_only || e.target.tagName === 'INPUT' && e.target.type === 'text') return;
      const key = e.key.toLowerCase();
      if ((e.ctrlKey || e.metaKey) && key === 'z') { e.preventDefault(); this.run(e.shiftKey ? '/api/redo' : '/api/undo', {}); }
      else if ((e.ctrlKey || e.metaKey) && key === 'y') { e.preventDefault(); this.run('/api/redo', {}); }
      else if ((e.ctrlKey || e.metaKey) && key === 's') { e.preventDefault(); this.save(); }
      else if (key === 'enter' && this.mode === 'polygon') this.finishPolygon();
      else if (key === 'escape') this.cancelPolygon();
    });
  }

  markView() {
    for (const view of ['free', 'top', 'front', 'side']) $(`view-${view}`).classList.toggle('active', this.viewer.view === view);
  }

  setMode(mode) {
    this.mode = mode;
    $('pick-points').classList.toggle('active', mode === 'pick');
    $('draw-polygon').classList.toggle('active', mode === 'polygon');
    $('overlay').classList.toggle('drawing', mode === 'polygon');
  }

  // --- 2D: polygon -------------------------------------------------------------------------

  startPolygon() {
    if (this.viewer.view === 'free') this.viewer.controls.enabled = false; // the view is fixed while drawing
    this.polygon = [];
    this.polygonClosed = false;
    this.setMode('polygon');
    this.drawPolygon();
    $('finish-polygon').disabled = false;
    $('cancel-polygon').disabled = false;
  }

  addVertex(e) {
    if (this.mode !== 'polygon' || this.polygonClosed) return;
    const rect = $('overlay').getBoundingClientRect();
    this.polygon.push([e.clientX - rect.left, e.clientY - rect.top]);
    this.drawPolygon();
  }

  finishPolygon() {
    if (this.mode !== 'polygon') return;
    // a double click adds the same vertex twice
    this.polygon = this.polygon.filter((p, i, all) => i === 0 || Math.hypot(p[0] - all[i - 1][0], p[1] - all[i - 1][1]) > 2);
    if (this.polygon.length < 3) { this.showError('a polygon needs at least 3 vertices'); return; }
    this.polygonClosed = true;
    this.drawPolygon();
    $('keep-inside').disabled = false;
    $('keep-outside').disabled = false;
    $('finish-polygon').disabled = true;
  }

  cancelPolygon() {
    this.polygon = [];
    this.polygonClosed = false;
    this.viewer.controls.enabled = true;
    if (this.mode === 'polygon') this.setMode('orbit');
    this.drawPolygon();
    for (const id of ['finish-polygon', 'keep-inside', 'keep-outside', 'cancel-polygon']) $(id).disabled = true;
  }

  drawPolygon() {
    const overlay = $('overlay');
    overlay.innerHTML = '';
    if (!this.polygon.length) return;
    const shape = document.createElementNS('http://www.w3.org/2000/svg', this.polygonClosed ? 'polygon' : 'polyline');
    shape.setAttribute('points', this.polygon.map((p) => p.join(',')).join(' '));
    overlay.appendChild(shape);
  }

  async split(keep) {
    const rect = $('overlay').getBoundingClientRect();
    const ndc = this.polygon.map(([x, y]) => [(x / rect.width) * 2 - 1, 1 - (y / rect.height) * 2]);
    const body = { view_projection: this.viewer.viewProjection(), polygon: ndc, keep };
    this.cancelPolygon();
    await this.run('/api/split', body);
  }

  // --- 3D: pick and fit ---------------------------------------------------------------------

  pickAt(e) {
    if (this.mode !== 'pick') return;
    const point = this.viewer.pick(e.clientX, e.clientY);
    if (!point) { this.showError('no point under the cursor'); return; }
    this.picks.push(point);
    this.showPicks();
  }

  clearPicks() { this.picks = []; this.lastFit = null; this.showPicks(); }

  showPicks() {
    $('pick-count').textContent = `${this.picks.length} picked`;
    this.viewer.showPicks(this.picks);
  }

  async fit(refit) {
    if (!this.picks.length) { this.showError('pick points on the surface first'); return; }
    if (refit && this.lastFit !== null) {
      // a new tolerance replaces the last fit: undo it, fit again
      await this.run('/api/undo', {});
    }
    const body = { kind: $('model-kind').value, seeds: this.picks, tolerance_m: Number($('tolerance').value) };
    const data = await this.run('/api/fit', body);
    if (data) {
      const r = data.result;
      this.lastFit = r.entry_id;
      $('fit-result').textContent = `${r.model.kind}: ${r.n_inliers.toLocaleString()} inliers, rms ${(r.rms_m * 1000).toFixed(1)} mm`;
    }
  }

  // --- operations ----------------------------------------------------------------------------

  // Operations run one after the other, in the order they were asked for.
  run(path, body, clearPicks = false) {
    const next = this.queue.then(() => this.runNow(path, body, clearPicks));
    this.queue = next.catch(() => null);
    return next;
  }

  async runNow(path, body, clearPicks) {
    this.busy = true;
    this.showStatus();
    try {
      const data = await this.call(path, body);
      if (path !== '/api/fit') this.lastFit = null;
      if (clearPicks) this.clearPicks();
      this.showError('');
      await this.viewer.refreshStates();
      this.showSummary(data.summary);
      return data;
    } catch (error) {
      this.showError(error.message);
      return null;
    } finally {
      this.busy = false;
      this.showStatus();
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
    if (this.summary.read_only) {
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
    $('status').dataset.idle = String(!s.inFlight && !this.busy);
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
