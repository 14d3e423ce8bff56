// Point-cloud rendering: a level-of-detail octree streamed from the server, coarse first,
// under a point budget, refined by the screen size of each node's bounding sphere.
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

function heightRamp(t) {
  // blue -> cyan -> green -> yellow -> red
  const stops = [[0, 0, 255], [0, 255, 255], [0, 200, 0], [255, 255, 0], [255, 0, 0]];
  const x = Math.min(Math.max(t, 0), 1) * (stops.length - 1);
  const i = Math.min(Math.floor(x), stops.length - 2);
  const f = x - i;
  return stops[i].map((a, k) => a + (stops[i + 1][k] - a) * f);
}

export class Viewer {
  constructor(container, scan) {
    this.container = container;
    this.hierarchy = scan.hierarchy;
    this.palette = scan.classes.map((c) => {
      const v = parseInt(c.colour.slice(1), 16);
      return [(v >> 16) & 255, (v >> 8) & 255, v & 255];
    });
    this.nodes = this.hierarchy.nodes.map((info) => ({ info, object: null, data: null, state: null, loading: false }));
    const lo = this.hierarchy.bounds_min, hi = this.hierarchy.bounds_max;
    this.bounds = new THREE.Box3(new THREE.Vector3(...lo), new THREE.Vector3(...hi));
    this.centre = this.bounds.getCenter(new THREE.Vector3());
    this.extent = Math.max(...this.bounds.getSize(new THREE.Vector3()).toArray(), 1);
    this.colourMode = 'class';
    this.pointSize = 2;
    this.pointBudget = 2_000_000;
    this.dimOutside = true;
    this.hidden = new Array(this.palette.length).fill(false);
    this.inFlight = 0;
    this.listeners = [];

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
    this.picked = new THREE.Points(
      new THREE.BufferGeometry(),
      new THREE.PointsMaterial({ color: 0xff2020, size: 9, sizeAttenuation: false }),
    );
    this.picked.renderOrder = 1;
    this.picked.material.depthTest = false;
    this.scene.add(this.picked);
    this.setView('free');
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  onChange(listener) { this.listeners.push(listener); }
  emit() { for (const l of this.listeners) l(); }

  get camera() { return this.view === 'free' ? this.perspective : this.orthographic; }

  resize() {
    const w = this.container.clientWidth, h = this.container.clientHeight;
    this.renderer.setSize(w, h);
    this.perspective.aspect = w / Math.max(h, 1);
    this.perspective.updateProjectionMatrix();
    this.fitOrthographic();
    this.requestRender();
  }

  fitOrthographic() {
    const w = this.container.clientWidth, h = Math.max(this.container.clientHeight, 1);
    const half = this.extent * 0.55;
    const aspect = w / h;
    Object.assign(this.orthographic, { left: -half * aspect, right: half * aspect, top: half, bottom: -half });
    this.orthographic.updateProjectionMatrix();
  }

  // Fixed axis-aligned views (rotation disabled) for the 2D workflow; 'free' orbits.
  setView(view) {
    this.view = view;
    if (this.controls) this.controls.dispose();
    const c = this.centre, d = this.extent * 2;
    const camera = this.camera;
    if (view === 'free') {
      camera.position.set(c.x - this.extent * 0.6, c.y - this.extent * 0.6, c.z + this.extent * 0.5);
    } else {
      this.orthographic.zoom = 1;
      this.fitOrthographic();
      if (view === 'top') { camera.up.set(0, 1, 0); camera.position.set(c.x, c.y, c.z + d); }
      if (view === 'front') { camera.up.set(0, 0, 1); camera.position.set(c.x, c.y - d, c.z); }
      if (view === 'side') { camera.up.set(0, 0, 1); camera.position.set(c.x + d, c.y, c.z); }
    }
    camera.lookAt(c);
    this.controls = new OrbitControls(camera, this.renderer.domElement);
    this.controls.target.copy(c);
    this.controls.enableRotate = view === 'free';
    this.controls.screenSpacePanning = true;
    this.controls.addEventListener('change', () => this.requestRender(true));
    this.controls.update();
    this.requestRender(true);
  }

  requestRender(lod = false) {
    if (lod) this.lodDirty = true;
    if (this.frame) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = null;
      if (this.lodDirty) { this.lodDirty = false; this.updateLod(); }
      this.renderer.render(this.scene, this.camera);
    });
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
    const wanted = new Set();
    const queue = [{ id: 0, priority: Infinity }];
    let points = 0;
    while (queue.length) {
      queue.sort((a, b) => b.priority - a.priority);
      const { id } = queue.shift();
      const node = this.nodes[id];
      const b = node.info.bounds;
      const box = new THREE.Box3(new THREE.Vector3(b[0], b[1], b[2]), new THREE.Vector3(b[3], b[4], b[5]));
      if (!frustum.intersectsBox(box)) continue;
      if (points + node.info.count > this.pointBudget && points > 0) break;
      points += node.info.count;
      wanted.add(id);
      for (const child of node.info.children) {
        queue.push({ id: child, priority: this.screenSize(this.nodes[child]) });
      }
    }
    this.wanted = wanted;
    for (const node of this.nodes) {
      if (node.object) node.object.visible = wanted.has(node.info.id);
    }
    this.loadMore();
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
        this.loadMore();
        this.requestRender();
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
    this.colourNode(node);
    this.scene.add(node.object);
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
      this.setState(node, buffer);
      this.colourNode(node);
    }));
    this.requestRender();
  }

  colourNode(node) {
    const { positions, rgb, intensity } = node.data;
    const { cls, working, pred } = node.state;
    const colour = node.object ? node.object.geometry.getAttribute('rgbc') : null;
    const shown = node.object ? node.object.geometry.getAttribute('shown') : null;
    if (!colour) return;
    const out = colour.array, visible = shown.array;
    const zLow = this.hierarchy.bounds_min[2], zSpan = Math.max(this.hierarchy.bounds_max[2] - zLow, 1e-6);
    const mode = this.colourMode, palette = this.palette;
    for (let i = 0; i < node.info.count; i++) {
      let c;
      if (mode === 'rgb') c = [rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]];
      else if (mode === 'intensity') c = [intensity[i], intensity[i], intensity[i]];
      else if (mode === 'height') c = heightRamp((positions[3 * i + 2] - zLow) / zSpan);
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

  setPointSize(size) { this.material.uniforms.size.value = size; this.requestRender(); }
  setBudget(budget) { this.pointBudget = budget; this.requestRender(true); }

  stats() {
    let points = 0, nodes = 0;
    for (const node of this.nodes) if (node.object && node.object.visible) { points += node.info.count; nodes += 1; }
    return { points, nodes, inFlight: this.inFlight };
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
    const box = new THREE.Box3(new THREE.Vector3(...low), new THREE.Vector3(...high));
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
      camera.position.copy(centre).addScaledVector(direction, size * 1.2);
    }
    this.controls.update();
    this.requestRender(true);
    return true;
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
    const rect = this.renderer.domElement.getBoundingClientRect();
    let pixel;
    if (camera.isOrthographicCamera) pixel = (camera.top - camera.bottom) / camera.zoom / rect.height;
    else pixel = this.extent / rect.height;
    raycaster.params.Points.threshold = pixel * 4;
    const objects = this.nodes.filter((n) => n.object && n.object.visible).map((n) => n.object);
    for (const hit of raycaster.intersectObjects(objects, false)) {
      const node = hit.object.userData.node;
      if (this.hidden[node.state.cls[hit.index]]) continue;
      const p = node.data.positions;
      return [p[3 * hit.index], p[3 * hit.index + 1], p[3 * hit.index + 2]];
    }
    return null;
  }

  showPicks(picks) {
    this.picked.geometry.dispose();
    this.picked.geometry = new THREE.BufferGeometry();
    this.picked.geometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(picks.flat()), 3));
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
