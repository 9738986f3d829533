// The 3-D view of a job's decimated cloud (GET /jobs/{id}/results/points): points coloured by
// the detector that flagged them, unflagged ones by height; orbit, zoom and pan with the mouse.
import * as THREE from "three";
import { OrbitControls } from "/app/static/vendor/three/OrbitControls.js";

// One colour per detector, in the order of their bits; well apart from the grey of kept points.
const PALETTE = ["#e6194b", "#f58231", "#ffe119", "#3cb44b", "#42d4f4", "#4363d8", "#f032e6",
                 "#bfef45", "#fabed4", "#dcbeff", "#9a6324", "#aaffc3", "#808000", "#ffd8b1",
                 "#000075", "#469990"];
const BACKGROUND = 0x16191d;
const LOW = new THREE.Color("#3d4a5a");
const HIGH = new THREE.Color("#d9dee5");

// The binary layout of lidar_outliers/view.py: magic, JSON header, float32 xyz, uint16 flags.
export function parsePoints(buffer) {
  const magic = new TextDecoder().decode(new Uint8Array(buffer, 0, 8));
  if (magic !== "LOPOINTS") throw new Error("not a points answer");
  const size = new DataView(buffer).getUint32(8, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 12, size)));
  const n = header.points;
  const xyz = new Float32Array(buffer, 12 + size, 3 * n);
  const flags = new Uint16Array(buffer, 12 + size + 12 * n, n);
  return { header, xyz, flags };
}

export function detectorColours(bits) {
  const out = {};
  for (const [name, bit] of Object.entries(bits)) out[name] = PALETTE[Math.log2(bit) % 16];
  return out;
}

export class CloudView {
  constructor(container) {
    this.container = container;
    // preserveDrawingBuffer: the canvas can be read back (screenshots) after a frame
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio);
    this.renderer.setClearColor(BACKGROUND);
    container.replaceChildren(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.1, 1000);
    this.camera.up.set(0, 0, 1); // LiDAR clouds are z-up
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.render());
    this.resizer = new ResizeObserver(() => this.resize());
    this.resizer.observe(container);
    this.hidden = new Set();
    this.showKept = true;
  }

  show(data) {
    this.data = data;
    const { xyz, flags, header } = data;
    this.colours = detectorColours(header.bits);
    this.order = Object.entries(header.bits).sort((a, b) => a[1] - b[1]);
    const kept = [];
    const flagged = [];
    for (let i = 0; i < flags.length; i++) (flags[i] ? flagged : kept).push(i);
    this.flaggedIndex = flagged;
    this.measure();
    this.kept = this.points(kept, 2, (i, colour) => this.heightColour(xyz[3 * i + 2], colour));
    this.scene.add(this.kept);
    this.rebuildFlagged();
    this.resize();
    this.frame(); // after the first resize: the fit depends on the aspect
    this.render();
  }

  // Each detector's points among those drawn (a point flagged by two counts for both).
  counts() {
    const out = {};
    for (const [name, bit] of this.order) {
      let n = 0;
      for (const i of this.flaggedIndex) if (this.data.flags[i] & bit) n++;
      if (n) out[name] = n;
    }
    return out;
  }

  setDetector(name, visible) {
    if (visible) this.hidden.delete(name);
    else this.hidden.add(name);
    this.rebuildFlagged();
    this.render();
  }

  setKept(visible) {
    this.kept.visible = visible;
    this.render();
  }

  // A flagged point shows while any detector that flagged it is shown, in the colour of the
  // first of those.
  rebuildFlagged() {
    if (this.flagged) {
      this.scene.remove(this.flagged);
      this.flagged.geometry.dispose();
    }
    const shown = this.order.filter(([name]) => !this.hidden.has(name));
    const mask = shown.reduce((m, [, bit]) => m | bit, 0);
    const index = this.flaggedIndex.filter((i) => this.data.flags[i] & mask);
    this.flagged = this.points(index, 4, (i, colour) => {
      const [name] = shown.find(([, bit]) => this.data.flags[i] & bit);
      colour.set(this.colours[name]);
    });
    this.scene.add(this.flagged);
  }

  points(index, size, paint) {
    const { xyz } = this.data;
    const position = new Float32Array(3 * index.length);
    const colourArray = new Float32Array(3 * index.length);
    const colour = new THREE.Color();
    index.forEach((i, k) => {
      position.set(xyz.subarray(3 * i, 3 * i + 3), 3 * k);
      paint(i, colour);
      colourArray.set([colour.r, colour.g, colour.b], 3 * k);
    });
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(position, 3));
    geometry.setAttribute("color", new THREE.BufferAttribute(colourArray, 3));
    geometry.setDrawRange(0, index.length);
    const material = new THREE.PointsMaterial({ size, sizeAttenuation: false, vertexColors: true });
    return new THREE.Points(geometry, material);
  }

  heightColour(z, colour) {
    const t = Math.min(1, Math.max(0, (z - this.zLow) / (this.zHigh - this.zLow || 1)));
    colour.copy(LOW).lerp(HIGH, t);
  }

  // The box the camera frames and the heights the colour ramp of kept points spans: the middle
  // 98 % and 96 % of a sample, so that a few far outliers neither shrink the view nor flatten
  // the ramp.
  measure() {
    const { xyz } = this.data;
    const step = Math.max(1, Math.floor(xyz.length / 3 / 20000));
    const axes = [[], [], []];
    for (let i = 0; i < xyz.length; i += 3 * step) {
      for (let a = 0; a < 3; a++) axes[a].push(xyz[i + a]);
    }
    const quantile = (values, q) => values[Math.floor(q * (values.length - 1))] ?? 0;
    for (const values of axes) values.sort((a, b) => a - b);
    this.box = new THREE.Box3(
      new THREE.Vector3(...axes.map((v) => quantile(v, 0.01))),
      new THREE.Vector3(...axes.map((v) => quantile(v, 0.99))));
    this.zLow = quantile(axes[2], 0.02);
    this.zHigh = quantile(axes[2], 0.98);
  }

  // Look across the cloud's longer horizontal side from above, as close as keeps every corner
  // of its bounding box in sight.
  frame() {
    const box = this.box;
    const size = box.getSize(new THREE.Vector3());
    const centre = box.getCenter(new THREE.Vector3());
    const direction = size.x >= size.y ? new THREE.Vector3(0.3, -1, 0.8)
      : new THREE.Vector3(1, 0.3, 0.8);
    direction.normalize();
    let distance = Math.max(size.length(), 1e-3);
    const corner = new THREE.Vector3();
    for (let round = 0; round < 4; round++) {
      this.place(centre, direction, distance);
      let extent = 0;
      for (let i = 0; i < 8; i++) {
        corner.set(i & 1 ? box.max.x : box.min.x, i & 2 ? box.max.y : box.min.y,
                   i & 4 ? box.max.z : box.min.z).project(this.camera);
        extent = Math.max(extent, Math.abs(corner.x), Math.abs(corner.y));
      }
      distance *= Math.min(Math.max(extent / 0.9, 0.2), 5);
    }
    this.place(centre, direction, distance);
  }

  place(centre, direction, distance) {
    this.camera.position.copy(centre).addScaledVector(direction, distance);
    this.camera.near = distance / 1000;
    this.camera.far = distance * 20;
    this.camera.lookAt(centre);
    this.camera.updateProjectionMatrix();
    this.camera.updateMatrixWorld();
    this.controls.target.copy(centre);
    this.controls.update();
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.container;
    if (!w || !h) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() {
    if (!this.data) return;
    this.renderer.render(this.scene, this.camera);
    const drawn = (this.kept.visible ? this.kept.geometry.drawRange.count : 0)
      + this.flagged.geometry.drawRange.count;
    this.container.dataset.drawn = String(drawn);
  }

  dispose() {
    this.resizer.disconnect();
    this.controls.dispose();
    for (const object of [this.kept, this.flagged]) object?.geometry.dispose();
    this.renderer.dispose();
    this.container.replaceChildren();
  }
}
