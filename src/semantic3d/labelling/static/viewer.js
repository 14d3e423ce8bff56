// Point-cloud rendering: a level-of-detail octree streamed from the server, coarse first.
//
// - Budget: nodes are chosen by their size on screen under a point budget, coarse first.
// - Frames: each frame draws at most ``framePoints`` points, a number that follows the
//   measured frame time. The points accumulate in an off-screen buffer: a camera move clears
//   it and draws the first slice (so a moving view, from its first frame, costs one slice);
//   when the camera rests, the following frames add slices of nodes without clearing, until
//   the full budget is drawn. The screen is that buffer plus the overlays (picks, measures,
//   regions), which change without redrawing the points. A node's buffers reach the GPU with
//   the slice that first draws it, so uploads are bounded per frame too. A pointer press or
//   a wheel step stops the refinement before the first frame of the move; nodes load only
//   when the camera rests.
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
// Points drawn in one frame (a moving view, or one slice of a refinement) follow the
// measured frame times so that a frame takes about FRAME_TARGET_MS.
const FRAME_TARGET_MS = 50;
const MIN_FRAME_POINTS = 30_000;
const START_FRAME_POINTS = 100_000;
const COPY_VERTEX = `
varying vec2 vUv;
void main() { vUv = uv; gl_Position = vec4(position.xy, 0.0, 1.0); }`;
const COPY_FRAGMENT = `
uniform sampler2D map;
varying vec2 vUv;
void main() { gl_FragColor = texture2D(map, vUv); }`;
export const RAMP = [[0, 0, 255], [0, 255, 255], [0, 200, 0], [255, 255, 0], [255, 0, 0]];

export function ramp(t) {
  // blue -> cyan -> green -> yellow -> red
  const x = Math.min(Math.max(t, 0), 1) * (RAMP.length - 1);
  const i = Math.min(Math.floor(x), RAMP.length - 2);
  const f = x - i;
  return RAMP[i].map((a, k) => a + (RAMP[i + 1][k] - a) * f);
}

// A max-heap of node ids by priority (the level-of-detail traversal pops the largest).
class Heap {
  constructor() { this.ids = []; this.keys = []; }
  get size() { return this.ids.length; }
  push(id, key) {
    const { ids, keys } = this;
    let i = ids.length;
    ids.push(id); keys.push(key);
    while (i > 0) {
      const parent = (i - 1) >> 1;
      if (keys[parent] >= key) break;
      ids[i] = ids[parent]; keys[i] = keys[parent];
      i = parent;
    }
    ids[i] = id; keys[i] = key;
  }
  pop() {
    const { ids, keys } = this;
    const top = ids[0];
    const id = ids.pop(), key = keys.pop();
    const n = ids.length;
    if (n) {
      let i = 0;
      for (;;) {
        let child = 2 * i + 1;
        if (child >= n) break;
        if (child + 1 < n && keys[child + 1] > keys[child]) child += 1;
        if (keys[child] <= key) break;
        ids[i] = ids[child]; keys[i] = keys[child];
        i = child;
      }
      ids[i] = id; keys[i] = key;
    }
    return top;
  }
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
    this.nodes = this.hierarchy.nodes.map((info) => {
      const b = info.bounds;
      const box = new THREE.Box3(new THREE.Vector3(b[0], b[1], b[2]), new THREE.Vector3(b[3], b[4], b[5]));
      const centre = box.getCenter(new THREE.Vector3());
      const radius = Math.hypot(b[3] - b[0], b[4] - b[1], b[5] - b[2]) / 2;
      return { info, box, centre, radius, object: null, data: null, state: null, paint: false, loading: false, lastUsed: 0 };
    });
    const lo = this.hierarchy.bounds_min, hi = this.hierarchy.bounds_max;
    this.bounds = new THREE.Box3(new THREE.Vector3(...lo), new THREE.Vector3(...hi));
    this.frame = new THREE.Box3().copy(this.bounds); // what the start view shows
    this.centre = this.bounds.getCenter(new THREE.Vector3());
    this.extent = Math.max(...this.bounds.getSize(new THREE.Vector3()).toArray(), 1);
    this.colourMode = 'class';
    this.pointSize = 2;
    this.pointBudget = 1_000_000;
    this.framePoints = START_FRAME_POINTS;
    this.adaptive = true; // false: every frame draws the full budget (a benchmark's fixed-budget row)
    this.memoryBudget = 4_000_000;
    this.dimOutside = true;
    this.hidden = new Array(this.palette.length).fill(false);
    this.ranges = { height: [lo[2], hi[2]], intensity: [0, 255] };
    this.autoRanges = null;
    this.inFlight = 0;
    this.listeners = [];
    this.tick = 0;
    this.order = []; // the nodes wanted under the budget, in the order they are drawn
    this.wanted = new Set();
    this.drawn = new Set(); // nodes in the off-screen buffer since it was last cleared
    this.drawnPoints = 0;
    this.stale = true; // the picture must be cleared and drawn again
    this.buffered = false; // the off-screen buffer holds the nodes drawn
    this.userMoved = false; // a move not yet drawn
    this.interacting = false; // a pointer is pressed on the view
    this.lastMove = -Infinity;
    this.lastFrame = 0;
    this.wantedSince = null; // when the next frame was first asked for (an input's time)
    this.inputSince = null;
    this.lastFramePoints = 0;
    this.lastFrameFull = false;
    this.holdFrames = 0;
    this.quickFrames = 0;
    this.loadedPoints = 0;
    this.evicted = 0;

    this.renderer = new THREE.WebGLRenderer({ antialias: false });
    this.renderer.setPixelRatio(1);
    this.renderer.setClearColor(0x111111);
    this.renderer.autoClear = false;
    container.prepend(this.renderer.domElement);
    this.scene = new THREE.Scene(); // the nodes' points
    this.overlayScene = new THREE.Scene();
    this.target = new THREE.WebGLRenderTarget(1, 1, {
      minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter, generateMipmaps: false, depthBuffer: true,
    });
    this.copyScene = new THREE.Scene();
    const copy = new THREE.Mesh(new THREE.PlaneGeometry(2, 2), new THREE.ShaderMaterial({
      uniforms: { map: { value: this.target.texture } },
      vertexShader: COPY_VERTEX,
      fragmentShader: COPY_FRAGMENT,
      depthTest: false,
      depthWrite: false,
    }));
    copy.frustumCulled = false;
    this.copyScene.add(copy);
    this.copyCamera = new THREE.OrthographicCamera(-1, 1, 1, -1, 0, 1);
    this.material = new THREE.ShaderMaterial({
      uniforms: { size: { value: this.pointSize } },
      vertexShader: VERTEX,
      fragmentShader: FRAGMENT,
    });
    this.perspective = new THREE.PerspectiveCamera(60, 1, this.extent / 1e4, this.extent * 20);
    this.perspective.up.set(0, 0, 1);
    this.orthographic = new THREE.OrthographicCamera(-1, 1, 1, -1, -this.extent * 20, this.extent * 20);
    this.overlay = new THREE.Group();
    this.overlayScene.add(this.overlay);
    this.picked = this.addOverlayPoints(0xff2020, 9);
    this.previewPoints = this.addOverlayPoints(0xffff00, 3);
    this.measureLine = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: 0xff60ff, depthTest: false }));
    this.overlay.add(this.measureLine);
    this.regionObject = null;
    this.setView('free');
    // The time of the first input of a move, so that a frame's time counts from it.
    const input = (e) => {
      if (this.inputSince === null && (e.type === 'wheel' || e.buttons)) {
        const first = e.getCoalescedEvents ? e.getCoalescedEvents()[0] : null;
        this.inputSince = (first || e).timeStamp;
      }
    };
    this.renderer.domElement.addEventListener('pointermove', input, { capture: true, passive: true });
    this.renderer.domElement.addEventListener('wheel', input, { capture: true, passive: true });
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
    this.target.setSize(Math.max(w, 1), Math.max(h, 1));
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
    const previous = this.view ? {
      position: this.camera.position.clone(), target: this.controls.target.clone(),
      orthographic: this.camera.isOrthographicCamera, zoom: this.orthographic.zoom,
    } : null;
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
        // The same scale: a 2D view's zoom, or the orbit view's at the target's depth.
        const halfHeight = distance * Math.tan((this.perspective.fov * Math.PI) / 360);
        this.orthographic.zoom = previous.orthographic ? previous.zoom : (this.extent * 0.55) / Math.max(halfHeight, 1e-3);
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
    // A press or a wheel step: the refinement stops before the first frame of the move.
    this.controls.addEventListener('start', () => { this.interacting = true; this.lastMove = performance.now(); });
    this.controls.addEventListener('end', () => { this.interacting = false; this.cameraRests(); });
    this.jump(() => this.controls.update());
    this.requestRender(true);
    this.emit();
  }

  // A view set by the program (a view button, framing, a restored view) is drawn at once and
  // refined like a resting one; a move by the user (or a script orbiting) pauses loading.
  jump(change) {
    this.jumping = true;
    try { change(); } finally { this.jumping = false; }
  }

  cameraMoved() {
    if (this.jumping) { this.requestRender(true); return; }
    this.userMoved = true;
    this.lastMove = performance.now();
    this.requestRender(true, this.inputSince ?? performance.now());
    this.cameraRests();
  }

  // Refine once the camera has rested SETTLE_MS after the last frame that showed it moving
  // (counted from that frame, so a slow frame cannot end a move).
  cameraRests() {
    clearTimeout(this.settleTimer);
    this.settleTimer = setTimeout(() => this.scheduleFrame(), SETTLE_MS + 10);
  }

  // Refine up to the full budget now (as if the camera had rested).
  settleNow() {
    clearTimeout(this.settleTimer);
    this.interacting = false;
    this.userMoved = false;
    this.lastMove = -Infinity;
    this.scheduleFrame();
    this.emit();
  }

  get moving() {
    return this.interacting || this.userMoved || performance.now() - this.lastMove < SETTLE_MS;
  }

  // Something drawn changed (the view, colours, sizes, hidden classes): the points are drawn
  // again from a cleared buffer, ``lod`` when the nodes wanted may have changed too.
  requestRender(lod = false, since = performance.now()) {
    if (lod) this.lodDirty = true;
    this.stale = true;
    this.scheduleFrame(since);
  }

  // Only the overlays changed: the screen is the buffer again with the overlays on top.
  requestOverlay() {
    this.overlayChanged = true;
    this.scheduleFrame();
  }

  scheduleFrame(since = performance.now()) {
    if (this.wantedSince === null || since < this.wantedSince) this.wantedSince = since;
    if (this.pending) return;
    this.pending = requestAnimationFrame((now) => this.drawFrame(now));
  }

  drawFrame(now) {
    this.pending = null;
    this.learnFrameTime(now);
    if (this.userMoved) { this.userMoved = false; this.lastMove = Math.max(this.lastMove, now); }
    if (this.lodDirty) { this.lodDirty = false; this.updateLod(); }
    for (const id of this.drawn) if (!this.wanted.has(id)) { this.stale = true; break; }
    // While moving, each frame is the first slice of a fresh picture, drawn straight to the
    // screen; at rest, slices add up in the off-screen buffer.
    const moving = this.moving;
    if (moving ? this.overlayChanged && !this.buffered : !this.buffered) this.stale = true;
    const clear = this.stale;
    if (clear) { this.stale = false; this.drawn.clear(); this.drawnPoints = 0; }
    let slice = { nodes: [], points: 0, full: false };
    if (moving && clear) {
      slice = this.nextSlice();
      this.draw(slice.nodes, null);
      this.buffered = false;
    } else if (!moving) {
      slice = this.nextSlice();
      if (clear || slice.nodes.length || this.overlayChanged) this.draw(slice.nodes, this.target, clear);
      this.buffered = true;
    } else if (this.overlayChanged) this.draw([], this.target, false);
    this.overlayChanged = false;
    this.lastFramePoints = slice.points;
    this.lastFrameFull = slice.full;
    if (!moving) {
      this.loadMore();
      if (this.order.some((id) => !this.drawn.has(id) && this.nodes[id].object)) this.scheduleFrame();
    } else if (!this.interacting) this.cameraRests();
    this.emit();
  }

  // The next nodes to draw, in order, up to ``framePoints`` points (at least one node).
  nextSlice() {
    const nodes = [];
    let points = 0, full = false;
    for (const id of this.order) {
      const node = this.nodes[id];
      if (this.drawn.has(id) || !node.object) continue;
      if (points > 0 && points + node.info.count > this.framePoints) { full = true; break; }
      nodes.push(node);
      points += node.info.count;
    }
    return { nodes, points, full };
  }

  // Draw ``nodes`` on the screen (``target`` null: a cleared screen) or into the off-screen
  // buffer (cleared first if ``clear``) and then the buffer on the screen; overlays on top.
  draw(nodes, target, clear = true) {
    const renderer = this.renderer;
    renderer.setRenderTarget(target);
    if (clear) renderer.clear();
    if (nodes.length) {
      for (const node of nodes) {
        if (node.paint) this.paintNode(node);
        node.object.visible = true;
        this.drawn.add(node.info.id);
        this.drawnPoints += node.info.count;
      }
      renderer.render(this.scene, this.camera);
      for (const node of nodes) node.object.visible = false;
    }
    if (target) {
      renderer.setRenderTarget(null);
      renderer.render(this.copyScene, this.copyCamera); // covers the whole screen: no clear
    }
    renderer.render(this.overlayScene, this.camera);
  }

  // The points per frame follow the time each frame took: from when it was asked for (an
  // input's time, or the request) or the previous frame's start, whichever is later, to its
  // start. A frame that takes too long lowers them at once; three frames in a row, each asked
  // for while the previous one was drawn, that took under 3/4 of the target and were limited
  // by them raise them by 10 %. After a change the next two frames are not counted (they were
  // queued before it).
  learnFrameTime(now) {
    const previous = this.lastFrame;
    const since = this.wantedSince ?? now;
    this.lastFrame = now;
    this.wantedSince = null;
    this.inputSince = null;
    const drew = this.lastFramePoints, full = this.lastFrameFull;
    this.lastFramePoints = 0;
    if (!this.adaptive) { this.framePoints = this.pointBudget; return; }
    if (!drew) return;
    const milliseconds = now - Math.max(previous, since);
    if (milliseconds > 1000) return;
    if (this.holdFrames > 0) { this.holdFrames -= 1; return; }
    if (milliseconds > FRAME_TARGET_MS * 1.3) {
      const factor = Math.min(Math.max(FRAME_TARGET_MS / milliseconds, 0.5), 0.8);
      const floor = Math.min(MIN_FRAME_POINTS, this.framePoints);
      this.framePoints = Math.max(floor, Math.round(this.framePoints * factor));
      this.holdFrames = 2;
      this.quickFrames = 0;
      return;
    }
    const backToBack = since - previous < 20;
    this.quickFrames = backToBack && full && milliseconds < FRAME_TARGET_MS * 0.75 ? this.quickFrames + 1 : 0;
    if (this.quickFrames >= 3) {
      this.framePoints = Math.min(this.pointBudget, Math.round(this.framePoints * 1.1));
      this.holdFrames = 2;
      this.quickFrames = 0;
    }
  }

  // --- level of detail ---------------------------------------------------------------------

  screenSize(node) {
    const h = this.container.clientHeight;
    const camera = this.camera;
    if (camera.isOrthographicCamera) {
      return (node.radius * camera.zoom * h) / (camera.top - camera.bottom);
    }
    const distance = Math.max(camera.position.distanceTo(node.centre) - node.radius, 1e-3);
    return (node.radius / distance) * (h / 2) / Math.tan((camera.fov * Math.PI) / 360);
  }

  // The nodes in view under the point budget, the largest on screen first (a binary heap).
  updateLod() {
    const camera = this.camera;
    camera.updateMatrixWorld();
    const frustum = new THREE.Frustum().setFromProjectionMatrix(
      new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse),
    );
    const budget = this.pointBudget;
    const order = [];
    const heap = new Heap();
    heap.push(0, Infinity);
    let points = 0;
    this.tick += 1;
    while (heap.size) {
      const node = this.nodes[heap.pop()];
      if (!frustum.intersectsBox(node.box)) continue;
      if (points + node.info.count > budget && points > 0) break;
      points += node.info.count;
      order.push(node.info.id);
      node.lastUsed = this.tick;
      for (const child of node.info.children) heap.push(child, this.screenSize(this.nodes[child]));
    }
    this.order = order;
    this.wanted = new Set(order);
    this.evict();
  }

  // Dispose the least recently shown nodes while more points than the memory budget are loaded.
  evict() {
    if (this.loadedPoints <= this.memoryBudget) return;
    const candidates = this.nodes
      .filter((n) => n.object && !this.wanted.has(n.info.id) && !this.drawn.has(n.info.id) && n.info.id !== 0)
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
        this.scheduleFrame(); // drawn by the next slice
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
    node.object.visible = false; // drawn only with its slice
    node.paint = true; // coloured by the slice that first draws it
    this.loadedPoints += n;
    this.scene.add(node.object);
    if (node.info.id === 0) this.learnFromRoot(node);
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
      node.paint = true;
    }));
    this.requestRender();
  }

  // Colour a node's points (done when a slice is about to draw it, so at most a slice's
  // points are coloured and uploaded in a frame).
  paintNode(node) {
    node.paint = false;
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
    for (const node of this.nodes) if (node.object) node.paint = true;
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
    this.framePoints = Math.min(this.framePoints, budget);
    this.memoryBudget = Math.max(this.memoryBudget, Math.round(budget * 1.5));
    this.requestRender(true);
  }

  // ``moving``: the camera moves or the view is not yet drawn up to its budget.
  stats() {
    const refining = this.stale || this.order.some((id) => !this.drawn.has(id));
    return {
      points: this.drawnPoints, nodes: this.drawn.size, inFlight: this.inFlight, loadedPoints: this.loadedPoints,
      evicted: this.evicted, framePoints: this.framePoints, moving: this.moving || refining,
    };
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
    this.jump(() => this.controls.update());
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
    this.jump(() => this.controls.update());
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
    const objects = [...this.drawn].map((id) => this.nodes[id].object).filter(Boolean);
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
    this.requestOverlay();
  }

  showPicks(picks) { this.setOverlayPoints(this.picked, picks); }
  showPreview(points) { this.setOverlayPoints(this.previewPoints, points); }

  showMeasure(points) {
    this.measureLine.geometry.dispose();
    this.measureLine.geometry = new THREE.BufferGeometry();
    this.measureLine.geometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(points.flat()), 3));
    this.requestOverlay();
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
    this.requestOverlay();
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
