// Selection in a fixed view: polygon (clicks), lasso (drag) and brush (paint).
//
// A polygon is sent as its vertices (NDC); a lasso or brush stroke is rasterised on the
// page's canvas and sent as a bit mask of the screen, with the camera it was drawn in. The
// server applies either to every working point of the scan.
const $ = (id) => document.getElementById(id);

// The painted pixels of a canvas as base64 bits (row by row from the top-left, little bit order).
export function canvasMask(canvas) {
  const { width, height } = canvas;
  const alpha = canvas.getContext('2d').getImageData(0, 0, width, height).data;
  const bits = new Uint8Array(Math.ceil((width * height) / 8));
  let painted = 0;
  for (let p = 0; p < width * height; p++) {
    if (alpha[4 * p + 3] > 0) { bits[p >> 3] |= 1 << (p & 7); painted += 1; }
  }
  let text = '';
  for (let i = 0; i < bits.length; i += 0x8000) text += String.fromCharCode(...bits.subarray(i, i + 0x8000));
  return { width, height, mask: btoa(text), painted };
}

export class SelectionTool {
  constructor(app) {
    this.app = app;
    this.kind = null;
    this.polygon = [];
    this.closed = false;
    this.stroke = null;
    this.shape = $('shape');
    this.canvas = $('paint');
    const overlay = $('overlay');
    // The shape is one persistent element that ignores the pointer: clicks land on the
    // overlay itself, so a double click is seen as one (rebuilding it under the pointer
    // made the browser drop the dblclick).
    overlay.addEventListener('click', (e) => this.addVertex(e));
    overlay.addEventListener('dblclick', (e) => { e.preventDefault(); this.close(); });
    this.canvas.addEventListener('pointerdown', (e) => this.paintStart(e));
    this.canvas.addEventListener('pointermove', (e) => this.paintMove(e));
    this.canvas.addEventListener('pointerup', (e) => this.paintEnd(e));
  }

  get active() { return this.kind !== null; }
  get ready() { return this.closed; }

  start(kind) {
    this.cancel();
    this.app.viewer.controls.enabled = false; // the view is fixed while selecting
    this.kind = kind;
    $('overlay').classList.toggle('drawing', kind === 'polygon');
    this.canvas.classList.toggle('painting', kind !== 'polygon');
    if (kind !== 'polygon') this.resetCanvas();
    for (const k of ['polygon', 'lasso', 'brush']) $(`draw-${k}`).classList.toggle('active', k === kind);
    $('finish-polygon').disabled = kind !== 'polygon';
    $('cancel-polygon').disabled = false;
    this.draw();
  }

  resetCanvas() {
    const stage = $('stage');
    this.canvas.width = stage.clientWidth;
    this.canvas.height = stage.clientHeight;
    const ctx = this.canvas.getContext('2d');
    ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
  }

  point(e) {
    const rect = $('stage').getBoundingClientRect();
    return [e.clientX - rect.left, e.clientY - rect.top];
  }

  addVertex(e) {
    if (this.kind !== 'polygon' || this.closed) return;
    this.polygon.push(this.point(e));
    this.draw();
  }

  removeVertex() {
    if (this.kind !== 'polygon' || this.closed || !this.polygon.length) return false;
    this.polygon.pop();
    this.draw();
    return true;
  }

  close() {
    if (this.kind === 'polygon') {
      // a double click adds the same vertex twice
      this.polygon = this.polygon.filter((p, i, all) => i === 0 || Math.hypot(p[0] - all[i - 1][0], p[1] - all[i - 1][1]) > 2);
      if (this.polygon.length < 3) { this.app.showError('a polygon needs at least 3 vertices'); return; }
    }
    this.closed = true;
    this.draw();
    $('keep-inside').disabled = false;
    $('keep-outside').disabled = false;
    $('finish-polygon').disabled = true;
  }

  paintStart(e) {
    if (!this.kind || this.kind === 'polygon') return;
    if (this.kind === 'lasso') this.resetCanvas();
    this.canvas.setPointerCapture(e.pointerId);
    this.stroke = [this.point(e)];
    this.paintMove(e);
  }

  paintMove(e) {
    if (!this.stroke) return;
    const p = this.point(e);
    const ctx = this.canvas.getContext('2d');
    if (this.kind === 'brush') {
      ctx.fillStyle = 'rgba(255, 220, 0, 0.35)';
      const r = Number($('brush-size').value) / 2;
      const last = this.stroke[this.stroke.length - 1];
      const steps = Math.max(1, Math.ceil(Math.hypot(p[0] - last[0], p[1] - last[1]) / (r / 2)));
      for (let s = 1; s <= steps; s++) { // circles along the segment: no gaps when moving fast
        const x = last[0] + ((p[0] - last[0]) * s) / steps, y = last[1] + ((p[1] - last[1]) * s) / steps;
        ctx.beginPath(); ctx.arc(x, y, r, 0, 2 * Math.PI); ctx.fill();
      }
    } else {
      ctx.strokeStyle = 'yellow'; ctx.lineWidth = 2;
      const last = this.stroke[this.stroke.length - 1];
      ctx.beginPath(); ctx.moveTo(...last); ctx.lineTo(...p); ctx.stroke();
    }
    this.stroke.push(p);
  }

  paintEnd() {
    if (!this.stroke) return;
    if (this.kind === 'lasso') {
      const stroke = this.stroke;
      this.resetCanvas();
      if (stroke.length >= 3) {
        const ctx = this.canvas.getContext('2d');
        ctx.fillStyle = 'rgba(255, 220, 0, 0.35)';
        ctx.beginPath(); ctx.moveTo(...stroke[0]);
        for (const p of stroke.slice(1)) ctx.lineTo(...p);
        ctx.closePath(); ctx.fill();
      }
    }
    this.stroke = null;
    this.close();
  }

  cancel() {
    this.kind = null;
    this.polygon = [];
    this.closed = false;
    this.stroke = null;
    this.app.viewer.controls.enabled = true;
    $('overlay').classList.remove('drawing');
    this.canvas.classList.remove('painting');
    this.resetCanvas();
    for (const k of ['polygon', 'lasso', 'brush']) $(`draw-${k}`).classList.remove('active');
    this.draw();
    for (const id of ['finish-polygon', 'keep-inside', 'keep-outside', 'cancel-polygon']) $(id).disabled = true;
  }

  draw() {
    this.shape.setAttribute('points', this.polygon.map((p) => p.join(',')).join(' '));
    this.shape.classList.toggle('open', !this.closed);
  }

  // The request that applies this selection (cleared afterwards).
  request(keep) {
    const viewer = this.app.viewer;
    const view_projection = viewer.viewProjection();
    let path, body;
    if (this.kind === 'polygon') {
      const rect = $('stage').getBoundingClientRect();
      const polygon = this.polygon.map(([x, y]) => [(x / rect.width) * 2 - 1, 1 - (y / rect.height) * 2]);
      path = '/api/split'; body = { view_projection, polygon, keep };
    } else {
      const { width, height, mask } = canvasMask(this.canvas);
      path = '/api/split-mask'; body = { view_projection, width, height, mask, keep };
    }
    this.cancel();
    return [path, body];
  }
}

// Picked points measured in the scan's own (georeferenced) frame.
export function describeMeasures(points, origin) {
  const fmt = (v) => v.toFixed(3);
  const lines = points.map((p, i) => `#${i + 1}  x ${fmt(p[0] + origin[0])}  y ${fmt(p[1] + origin[1])}  z ${fmt(p[2] + origin[2])}`);
  for (let i = 1; i < points.length; i++) {
    const [a, b] = [points[i - 1], points[i]];
    const dx = b[0] - a[0], dy = b[1] - a[1], dz = b[2] - a[2];
    lines.push(`#${i}→#${i + 1}  distance ${fmt(Math.hypot(dx, dy, dz))} m  horizontal ${fmt(Math.hypot(dx, dy))} m  height ${dz >= 0 ? '+' : ''}${fmt(dz)} m`);
  }
  return lines.join('\n');
}
