// Point-cloud rendering: a level-of-detail octree streamed from the server, coarse first.
//
// - Budget: nodes are chosen by their size on screen under a point budget. While the camera
//   moves, a lower budget adapts to the measured frame time (so orbiting stays interactive
//   on software WebGL); when it stops, the view refines up to the full budget.
// - Memory: loaded nodes are kept in a least-recently-used order; above the memory budget
//   (in points) the nodes not shown for longest are disposed.
// - Views: orbit (perspective), fixed 2D views along the axes (top, front, side) and a free
//   2D view along the current viewing direction (orthographic, rotation off); zoom to cursor.
import * as THREE from 'three';
import { OrbitControls } from '/static/vendor/three/OrbitControls.js';
import { apiBytes } from '/static/api.js';

const VERTEX = `
attribute vec3 rgbc;
attribute float shown;
uniform float size;
varying vec3 vColor;
void main() {
  vColor = rgbc;
  if (shown < 0.5) { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); gl_PointSize = 0.0; return; }
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
  gl_PointSize = size;
}`;
const FRAGMENT = `
varying vec3 vColor;
void main() { gl_FragColor = vec4(vColor, 1.0); }`;

const MAX_IN_FLIGHT = 4;
const SETTLE_MS = 250;
const MIN_MOVING_BUDGET = 50_000;
export const RAMP = [[0, 0, 255], [0, 255, 255], [0, 200, 0], [255, 255, 0], [255, 0, 0]];

export function ramp(t) {
  // blue -> cyan -> green -> yellow -> red
  const x = Math.min(Math.max(t, 0), 1) * (RAMP.length - 1);
  const i = Math.min(Math.floor(x), RAMP.length - 2);
  const f = x - i;
  return RAMP[i].map((a, k) => a + (RAMP[i + 1][k] - a) * f);
}

function percentile(sorted, q) {
  if (!sorted.length) return 0;
  return sorted[Math.min(sorted.length - 1, Math.max(0, Math.round(q * (sorted.length - 1))))];
}

export class Viewer {
  constructor(container, scan) {
    this.container = container;
    this.hierarchy = scan.hierarchy;
    this.origin = scan.hierarchy.origin;
    this.palette = scan.classes.map((c) => {
      const v = parseInt(c.colour.slice(1), 16);
      return [(v >> 16) & 255, (v >> 8) & 255, v & 255];
    });
    this.nodes = this.hierarchy.nodes.map((info) => ({
      info, object: null, data: null, state: null, loading: false, lastUsed: 0,
    }));
    const lo = this.hierarchy.bounds_min, hi = this.hierarchy.bounds_max;
    this.bounds = new THREE.Box3(new THREE.Vector3(...lo), new THREE.Vector3(...hi));
    this.frame = new THREE.Box3().copy(this.bounds); // what the start view shows
    this.centre = this.bounds.getCenter(new THREE.Vector3());
    this.extent = Math.max(...this.bounds.getSize(new THREE.Vector3()).toArray(), 1);
    this.colourMode = 'class';
    this.pointSize = 2;
    this.pointBudget = 1_000_000;
    this.movingBudget = 300_000;
    this.adaptive = true; // false: move at the full budget (a benchmark's fixed-budget row)
    this.memoryBudget = 4_000_000;
    this.dimOutside = true;
    this.hidden = new Array(this.palette.length).fill(false);
    this.ranges = { height: [lo[2], hi[2]], intensity: [0, 255] };
    this.autoRanges = null;
    this.inFlight = 0;
    this.listeners = [];
    this.tick = 0;
    this.movingUntil = 0;
    this.lastFrame = 0;
    this.frameTimes = [];
    this.loadedPoints = 0;
    this.evicted = 0;

    this.renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(1);
    this.renderer.setClearColor(0x111111);
    container.prepend(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.material = new THREE.ShaderMaterial({
      uniforms: { size: { value: this.pointSize } },
      vertexShader: VERTEX,
      fragmentShader: FRAGMENT,
    });
    this.perspective = new THREE.PerspectiveCamera(60, 1, this.extent / 1e4, this.extent * 20);
    this.perspective.up.set(0, 0, 1);
    this.orthographic = new THREE.OrthographicCamera(-1, 1, 1, -1, -this.extent * 20, this.extent * 20);
    this.overlay = new THREE.Group();
    this.overlay.renderOrder = 1;
    this.scene.add(this.overlay);
    this.picked = this.addOverlayPoints(0xff2020, 9);
    this.previewPoints = this.addOverlayPoints(0xffff00, 3);
    this.measureLine = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: 0xff60ff, depthTest: false }));
    this.overlay.add(this.measureLine);
    this.regionObject = null;
    this.setView('free');
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  addOverlayPoints(color, size) {
    const points = new THREE.Points(
      new THREE.BufferGeometry(),
      new THREE.PointsMaterial({ color, size, sizeAttenuation: false, depthTest: false }),
    );
    this.overlay.add(points);
    return points;
  }

  onChange(listener) { this.listeners.push(listener); }
  emit() { for (const l of this.listeners) l(); }

  get camera() { return this.view === 'free' ? this.perspective : this.orthographic; }
  get is2d() { return this.view !== 'free'; }

  resize() {
    const w = this.container.clientWidth, h = this.container.clientHeight;
    this.renderer.setSize(w, h);
    this.perspective.aspect = w / Math.max(h, 1);
    this.perspective.updateProjectionMatrix();
    this.fitOrthographic();
    this.requestRender(true);
  }

  fitOrthographic() {
    const w = this.container.clientWidth, h = Math.max(this.container.clientHeight, 1);
    const half = this.extent * 0.55;
    const aspect = w / h;
    Object.assign(this.orthographic, { left: -half * aspect, right: half * aspect, top: half, bottom: -half });
    this.orthographic.updateProjectionMatrix();
  }

  // Views: 'free' orbits; 'top', 'front', 'side' look along the axes; 'free2d' looks along
  // the current viewing direction. 2D views are orthographic with rotation off.
  setView(view) {
    const previous = this.view ? { position: this.camera.position.clone(), target: this.controls.target.clone() } : null;
    this.view = view;
    if (this.controls) this.controls.dispose();
    const c = previous ? previous.target : this.frame.getCenter(new THREE.Vector3());
    const size = Math.max(...this.frame.getSize(new THREE.Vector3()).toArray(), 1);
    const d = this.extent * 2;
    const camera = this.camera;
    if (view === 'free') {
      if (!previous) camera.position.set(c.x - size * 0.6, c.y - size * 0.6, c.z + size * 0.45);
      else camera.position.copy(previous.position);
      camera.up.set(0, 0, 1);
    } else {
      this.fitOrthographic();
      this.orthographic.zoom = (this.extent * 0.55) / (size * 0.55);
      if (view === 'top') { camera.up.set(0, 1, 0); camera.position.set(c.x, c.y, c.z + d); }
      if (view === 'front') { camera.up.set(0, 0, 1); camera.position.set(c.x, c.y - d, c.z); }
      if (view === 'side') { camera.up.set(0, 0, 1); camera.position.set(c.x + d, c.y, c.z); }
      if (view === 'free2d' && previous) {
        const direction = c.clone().sub(previous.position);
        const distance = Math.max(direction.length(), 1e-3);
        direction.normalize();
        camera.up.set(0, 0, 1);
        if (Math.abs(direction.z) > 0.999) camera.up.set(0, 1, 0);
        camera.position.copy(c).addScaledVector(direction, -d);
        const halfHeight = distance * Math.tan((this.perspective.fov * Math.PI) / 360);
        this.orthographic.zoom = (this.extent * 0.55) / Math.max(halfHeight, 1e-3);
      }
      this.orthographic.updateProjectionMatrix();
    }
    camera.lookAt(c);
    this.controls = new OrbitControls(camera, this.renderer.domElement);
    this.controls.target.copy(c);
    this.controls.enableRotate = view === 'free';
    this.controls.screenSpacePanning = true;
    this.controls.zoomToCursor = true;
    this.controls.addEventListener('change', () => this.cameraMoved());
    this.controls.update();
    this.requestRender(true);
    this.emit();
  }

  cameraMoved() {
    this.movingUntil = performance.now() + SETTLE_MS;
    this.cameraChanged = true; // moving until a frame is drawn, however long frames take
    this.requestRender(true);
    clearTimeout(this.settleTimer);
    this.settling = true; // the refinement after the stop is still to come
    this.settleTimer = setTimeout(() => this.settleNow(), SETTLE_MS + 20);
  }

  // The camera stopped: refine up to the full budget now.
  settleNow() {
    clearTimeout(this.settleTimer);
    this.settling = false;
    this.cameraChanged = false;
    this.movingUntil = 0;
    this.requestRender(true);
    this.emit();
  }

  get moving() { return this.cameraChanged || performance.now() < this.movingUntil; }

  requestRender(lod = false) {
    if (lod) this.lodDirty = true;
    if (this.pending) return;
    this.pending = requestAnimationFrame((now) => {
      this.pending = null;
      this.adaptBudget(now);
      if (this.lodDirty) { this.lodDirty = false; this.updateLod(); }
      this.renderer.render(this.scene, this.camera);
      this.cameraChanged = false;
      this.emit();
    });
  }

  // While moving, the budget follows the frame time: lower when frames are slow, higher when fast.
  adaptBudget(now) {
    const interval = now - this.lastFrame;
    this.lastFrame = now;
    if (!this.adaptive) { this.movingBudget = this.pointBudget; return; }
    if (!this.moving || interval > 1000) return;
    this.frameTimes.push(interval);
    if (this.frameTimes.length > 120) this.frameTimes.shift();
    if (interval > 60) this.movingBudget = Math.max(MIN_MOVING_BUDGET, Math.round(this.movingBudget * 0.7));
    else if (interval < 35) this.movingBudget = Math.min(this.pointBudget, Math.round(this.movingBudget * 1.1));
  }

  // --- level of detail ---------------------------------------------------------------------

  screenSize(node) {
    const b = node.info.bounds;
    const centre = new THREE.Vector3((b[0] + b[3]) / 2, (b[1] + b[4]) / 2, (b[2] + b[5]) / 2);
    const radius = Math.hypot(b[3] - b[0], b[4] - b[1], b[5] - b[2]) / 2;
    const h = this.container.clientHeight;
    const camera = this.camera;
    if (camera.isOrthographicCamera) {
      return (radius * camera.zoom * h) / (camera.top - camera.bottom);
    }
    const distance = Math.max(camera.position.distanceTo(centre) - radius, 1e-3);
    return (radius / distance) * (h / 2) / Math.tan((camera.fov * Math.PI) / 360);
  }

  updateLod() {
    const camera = this.camera;
    camera.updateMatrixWorld();
    const frustum = new THREE.Frustum().setFromProjectionMatrix(
      new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse),
    );
    const moving = this.moving;
    const budget = moving ? Math.min(this.movingBudget, this.pointBudget) : this.pointBudget;
    const wanted = new Set();
    const queue = [{ id: 0, priority: Infinity }];
    let points = 0;
    this.tick += 1;
    while (queue.length) {
      queue.sort((a, b) => b.priority - a.priority);
      const { id } = queue.shift();
      const node = this.nodes[id];
      const b = node.info.bounds;
      const box = new THREE.Box3(new THREE.Vector3(b[0], b[1], b[2]), new THREE.Vector3(b[3], b[4], b[5]));
      if (!frustum.intersectsBox(box)) continue;
      if (points + node.info.count > budget && points > 0) break;
      // While moving, only what is already loaded is drawn (loading waits for the stop).
      if (moving && !node.object && points > 0) continue;
      points += node.info.count;
      wanted.add(id);
      node.lastUsed = this.tick;
      for (const child of node.info.children) {
        queue.push({ id: child, priority: this.screenSize(this.nodes[child]) });
      }
    }
    this.wanted = wanted;
    for (const node of this.nodes) {
      if (node.object) node.object.visible = wanted.has(node.info.id);
    }
    this.evict();
    if (!moving) this.loadMore();
  }

  // Dispose the least recently shown nodes while more points than the memory budget are loaded.
  evict() {
    if (this.loadedPoints <= this.memoryBudget) return;
    const candidates = this.nodes
      .filter((n) => n.object && !this.wanted.has(n.info.id) && n.info.id !== 0)
      .sort((a, b) => a.lastUsed - b.lastUsed);
    for (const node of candidates) {
      if (this.loadedPoints <= this.memoryBudget) break;
      this.scene.remove(node.object);
      node.object.geometry.dispose();
      node.object = null;
      node.data = null;
      node.state = null;
      this.loadedPoints -= node.info.count;
      this.evicted += 1;
    }
  }

  loadMore() {
    if (!this.wanted) return;
    // Coarse first: ids are breadth first.
    for (const id of [...this.wanted].sort((a, b) => a - b)) {
      if (this.inFlight >= MAX_IN_FLIGHT) break;
      const node = this.nodes[id];
      if (node.object || node.loading) continue;
      node.loading = true;
      this.inFlight += 1;
      this.loadNode(node).catch((e) => console.error(e)).finally(() => {
        node.loading = false;
        this.inFlight -= 1;
        this.requestRender(true);
        this.emit();
      });
    }
  }

  async loadNode(node) {
    const n = node.info.count;
    const [pointsBuffer, stateBuffer] = await Promise.all([
      apiBytes(`/api/nodes/${node.info.id}`),
      apiBytes(`/api/nodes/${node.info.id}/state`),
    ]);
    node.data = {
      positions: new Float32Array(pointsBuffer, 0, 3 * n),
      rgb: new Uint8Array(pointsBuffer, 12 * n, 3 * n),
      intensity: new Uint8Array(pointsBuffer, 15 * n, n),
    };
    this.setState(node, stateBuffer);
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute('position', new THREE.BufferAttribute(node.data.positions, 3));
    geometry.setAttribute('rgbc', new THREE.BufferAttribute(new Uint8Array(3 * n), 3, true));
    geometry.setAttribute('shown', new THREE.BufferAttribute(new Uint8Array(n), 1, false));
    geometry.computeBoundingSphere();
    node.object = new THREE.Points(geometry, this.material);
    node.object.userData.node = node;
    node.object.visible = this.wanted ? this.wanted.has(node.info.id) : true;
    this.loadedPoints += n;
    if (node.info.id === 0) this.learnFromRoot(node);
    this.colourNode(node);
    this.scene.add(node.object);
  }

  // The root node is a uniform sample of the scan: the dense part frames the start view, and
  // 2-98 % percentiles give colour ranges that far returns and outliers do not flatten.
  learnFromRoot(node) {
    const p = node.data.positions, n = node.info.count;
    const axes = [[], [], []], intensity = Array.from(node.data.intensity).sort((a, b) => a - b);
    for (let i = 0; i < n; i++) for (let k = 0; k < 3; k++) axes[k].push(p[3 * i + k]);
    axes.forEach((a) => a.sort((x, y) => x - y));
    const low = axes.map((a) => percentile(a, 0.05)), high = axes.map((a) => percentile(a, 0.95));
    this.autoRanges = {
      height: [percentile(axes[2], 0.02), percentile(axes[2], 0.98)],
      intensity: [percentile(intensity, 0.02), Math.max(percentile(intensity, 0.98), percentile(intensity, 0.02) + 1)],
    };
    for (const key of ['height', 'intensity']) if (!this.userRanges?.[key]) this.ranges[key] = this.autoRanges[key];
    this.frame = new THREE.Box3(new THREE.Vector3(...low), new THREE.Vector3(...high));
    if (this.onDenseFrame) this.onDenseFrame();
    this.recolour();
  }

  setState(node, buffer) {
    const n = node.info.count;
    node.state = {
      cls: new Uint8Array(buffer, 0, n),
      working: new Uint8Array(buffer, n, n),
      pred: new Uint8Array(buffer, 2 * n, n),
    };
  }

  async refreshStates() {
    const loaded = this.nodes.filter((n) => n.object);
    await Promise.all(loaded.map(async (node) => {
      const buffer = await apiBytes(`/api/nodes/${node.info.id}/state`);
      if (!node.object) return; // evicted meanwhile
      this.setState(node, buffer);
      this.colourNode(node);
    }));
    this.requestRender();
  }

  colourNode(node) {
    if (!node.object) return;
    const { positions, rgb, intensity } = node.data;
    const { cls, working, pred } = node.state;
    const colour = node.object.geometry.getAttribute('rgbc');
    const shown = node.object.geometry.getAttribute('shown');
    const out = colour.array, visible = shown.array;
    const [zLow, zHigh] = this.ranges.height, zSpan = Math.max(zHigh - zLow, 1e-6);
    const [iLow, iHigh] = this.ranges.intensity, iSpan = Math.max(iHigh - iLow, 1e-6);
    const mode = this.colourMode, palette = this.palette;
    for (let i = 0; i < node.info.count; i++) {
      let c;
      if (mode === 'rgb') c = [rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]];
      else if (mode === 'intensity') { const g = Math.min(Math.max((intensity[i] - iLow) / iSpan, 0), 1) * 255; c = [g, g, g]; }
      else if (mode === 'height') c = ramp((positions[3 * i + 2] - zLow) / zSpan);
      else if (mode === 'prediction') c = pred[i] === 255 ? [90, 90, 90] : palette[pred[i]] || [90, 90, 90];
      else if (mode === 'errors') {
        c = cls[i] === 0 || pred[i] === 255 ? [90, 90, 90] : pred[i] === cls[i] ? [40, 180, 60] : [230, 30, 30];
      } else c = palette[cls[i]] || [255, 255, 255];
      const f = this.dimOutside && !working[i] ? 0.3 : 1;
      out[3 * i] = c[0] * f; out[3 * i + 1] = c[1] * f; out[3 * i + 2] = c[2] * f;
      visible[i] = this.hidden[cls[i]] ? 0 : 1;
    }
    colour.needsUpdate = true;
    shown.needsUpdate = true;
  }

  recolour() {
    for (const node of this.nodes) if (node.object) this.colourNode(node);
    this.requestRender();
  }

  setRange(kind, range) {
    this.userRanges = { ...(this.userRanges || {}), [kind]: range !== null };
    this.ranges[kind] = range || (this.autoRanges ? this.autoRanges[kind] : this.ranges[kind]);
    this.recolour();
  }

  setPointSize(size) { this.pointSize = size; this.material.uniforms.size.value = size; this.requestRender(); }
  setBudget(budget) {
    this.pointBudget = budget;
    this.movingBudget = Math.min(this.movingBudget, budget);
    this.memoryBudget = Math.max(this.memoryBudget, Math.round(budget * 1.5));
    this.requestRender(true);
  }

  stats() {
    let points = 0, nodes = 0;
    for (const node of this.nodes) if (node.object && node.object.visible) { points += node.info.count; nodes += 1; }
    return { points, nodes, inFlight: this.inFlight, loadedPoints: this.loadedPoints, evicted: this.evicted, movingBudget: this.movingBudget, moving: this.moving || Boolean(this.settling) };
  }

  // --- view state (remembered across reloads) ---------------------------------------------------

  viewState() {
    const camera = this.camera;
    return {
      view: this.view,
      position: camera.position.toArray(),
      target: this.controls.target.toArray(),
      up: camera.up.toArray(),
      zoom: this.orthographic.zoom,
    };
  }

  restoreView(state) {
    if (!state || !state.view) return false;
    this.setView(state.view);
    const camera = this.camera;
    camera.position.fromArray(state.position);
    camera.up.fromArray(state.up);
    this.controls.target.fromArray(state.target);
    if (camera.isOrthographicCamera) { camera.zoom = state.zoom; camera.updateProjectionMatrix(); }
    camera.lookAt(this.controls.target);
    this.controls.update();
    this.requestRender(true);
    return true;
  }

  // Frame the box ``frame`` (the dense part of the scan) from the current direction.
  frameBox(box) {
    const centre = box.getCenter(new THREE.Vector3());
    const size = Math.max(...box.getSize(new THREE.Vector3()).toArray(), 1);
    const camera = this.camera;
    camera.position.add(centre.clone().sub(this.controls.target));
    this.controls.target.copy(centre);
    if (camera.isOrthographicCamera) {
      camera.zoom = (camera.top - camera.bottom) / (size * 1.1);
      camera.updateProjectionMatrix();
    } else {
      const direction = camera.position.clone().sub(centre).normalize();
      camera.position.copy(centre).addScaledVector(direction, size * 1.1);
    }
    this.controls.update();
    this.requestRender(true);
  }

  // Centre the view on the loaded points of the working set, zoomed to fit them.
  frameWorking() {
    const low = [Infinity, Infinity, Infinity], high = [-Infinity, -Infinity, -Infinity];
    for (const node of this.nodes) {
      if (!node.object) continue;
      const p = node.data.positions, w = node.state.working;
      for (let i = 0; i < node.info.count; i++) {
        if (!w[i]) continue;
        for (let k = 0; k < 3; k++) {
          const v = p[3 * i + k];
          if (v < low[k]) low[k] = v;
          if (v > high[k]) high[k] = v;
        }
      }
    }
    if (low[0] === Infinity) return false;
    this.frameBox(new THREE.Box3(new THREE.Vector3(...low), new THREE.Vector3(...high)));
    return true;
  }

  // Metres per screen pixel at the target (2D views: exact; orbit: at the target's depth).
  metresPerPixel() {
    const h = Math.max(this.container.clientHeight, 1);
    const camera = this.camera;
    if (camera.isOrthographicCamera) return (camera.top - camera.bottom) / camera.zoom / h;
    const distance = camera.position.distanceTo(this.controls.target);
    return (2 * distance * Math.tan((camera.fov * Math.PI) / 360)) / h;
  }

  // Unit world vectors along the screen's right and up directions.
  screenAxes() {
    const camera = this.camera;
    camera.updateMatrixWorld();
    const e = camera.matrixWorld.elements;
    return { right: [e[0], e[1], e[2]], up: [e[4], e[5], e[6]] };
  }

  // --- picking and projection ------------------------------------------------------------------

  ndcOf(clientX, clientY) {
    const rect = this.renderer.domElement.getBoundingClientRect();
    return [((clientX - rect.left) / rect.width) * 2 - 1, 1 - ((clientY - rect.top) / rect.height) * 2];
  }

  pick(clientX, clientY) {
    const [x, y] = this.ndcOf(clientX, clientY);
    const raycaster = new THREE.Raycaster();
    const camera = this.camera;
    raycaster.setFromCamera(new THREE.Vector2(x, y), camera);
    raycaster.params.Points.threshold = this.metresPerPixel() * 6;
    const objects = this.nodes.filter((n) => n.object && n.object.visible).map((n) => n.object);
    for (const hit of raycaster.intersectObjects(objects, false)) {
      const node = hit.object.userData.node;
      if (this.hidden[node.state.cls[hit.index]]) continue;
      const p = node.data.positions;
      return [p[3 * hit.index], p[3 * hit.index + 1], p[3 * hit.index + 2]];
    }
    return null;
  }

  setOverlayPoints(object, points) {
    object.geometry.dispose();
    object.geometry = new THREE.BufferGeometry();
    object.geometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(points.flat()), 3));
    this.requestRender();
  }

  showPicks(picks) { this.setOverlayPoints(this.picked, picks); }
  showPreview(points) { this.setOverlayPoints(this.previewPoints, points); }

  showMeasure(points) {
    this.measureLine.geometry.dispose();
    this.measureLine.geometry = new THREE.BufferGeometry();
    this.measureLine.geometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(points.flat()), 3));
    this.requestRender();
  }

  // A wireframe of the fit's region (``null`` removes it).
  showRegion(region) {
    if (this.regionObject) { this.overlay.remove(this.regionObject); this.regionObject.geometry.dispose(); this.regionObject = null; }
    if (region) {
      let geometry;
      if (region.kind === 'sphere') {
        geometry = new THREE.WireframeGeometry(new THREE.SphereGeometry(region.radius_m, 16, 10));
        geometry.translate(...region.centre);
      } else {
        const size = region.max.map((v, k) => v - region.min[k]);
        geometry = new THREE.WireframeGeometry(new THREE.BoxGeometry(...size));
        geometry.translate(...region.max.map((v, k) => (v + region.min[k]) / 2));
      }
      this.regionObject = new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({ color: 0x40c0ff, depthTest: false }));
      this.overlay.add(this.regionObject);
    }
    this.requestRender();
  }

  // Row-major view-projection matrix (clip = M [x y z 1]) of the current camera.
  viewProjection() {
    const camera = this.camera;
    camera.updateMatrixWorld();
    const m = new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse);
    return m.transpose().elements.slice();
  }

  // Client pixel coordinates of a re-centred scene point (for scripted use and tests).
  toClient(x, y, z) {
    const v = new THREE.Vector3(x, y, z).project(this.camera);
    const rect = this.renderer.domElement.getBoundingClientRect();
    return [rect.left + ((v.x + 1) / 2) * rect.width, rect.top + ((1 - v.y) / 2) * rect.height];
  }
}
