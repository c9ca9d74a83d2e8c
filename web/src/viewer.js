// The 3D view of one or two occupancy grids (three.js): coloured cubes (only the faces between shown and hidden
// voxels are drawn), the ego vehicle, the six camera frusta, orbit/zoom/pan, per-class toggles, the mask_camera
// toggle, panes side by side or one at a time, camera thumbnails. No network: everything comes in `data`.
//
// data (what occflownet/viewer writes, or what the server page builds from the API's answer):
//   {title, shape: [X, Y, Z], lower: [x, y, z], voxel_size, free_index, classes: [names], colors: [[r, g, b]],
//    grids: [{name, occupancy: {data, encoding}, mask_camera?: {data, encoding}}],
//    cameras: [{name, intrinsic: 3x3, cam2ego: 4x4, image_size: [w, h], image?: data URL}]}
import {
  BufferAttribute, BufferGeometry, Color, EdgesGeometry, BoxGeometry, Group, LineBasicMaterial, LineSegments,
  LinearSRGBColorSpace, Mesh, MeshBasicMaterial, PerspectiveCamera, Scene, WebGLRenderer,
} from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
import { classCounts, decodeBytes, facingRanges, surface } from "./grid.js";

const BACKGROUND = 0xf2f3f5;
const FRUSTUM_DEPTH = 4.0;                      // metres drawn along each camera's view
const FRUSTUM_COLOR = 0x222222, FRUSTUM_HOVER = 0xff3300;
// nuScenes ego vehicle, ego frame (origin at the rear axle, on the ground): about 4.1 × 1.8 × 1.6 m.
const EGO = { min: [-0.9, -0.9, 0.0], max: [3.2, 0.9, 1.6] };

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v;
    else if (k === "style") e.style.cssText = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

function hex(rgb) { return "#" + rgb.map((c) => c.toString(16).padStart(2, "0")).join(""); }

function frustumLines(cam) {
  // apex at the camera centre, four edges to the image corners at FRUSTUM_DEPTH, and the far rectangle
  const K = cam.intrinsic, T = cam.cam2ego, [w, h] = cam.image_size;
  const toEgo = (p) => [0, 1, 2].map((r) => T[r][0] * p[0] + T[r][1] * p[1] + T[r][2] * p[2] + T[r][3]);
  const corner = (u, v) => {
    const x = (u - K[0][2]) / K[0][0], y = (v - K[1][2]) / K[1][1];
    return toEgo([x * FRUSTUM_DEPTH, y * FRUSTUM_DEPTH, FRUSTUM_DEPTH]);
  };
  const apex = toEgo([0, 0, 0]);
  const c = [corner(-0.5, -0.5), corner(w - 0.5, -0.5), corner(w - 0.5, h - 0.5), corner(-0.5, h - 0.5)];
  const seg = [];
  for (let i = 0; i < 4; i++) seg.push(...apex, ...c[i], ...c[i], ...c[(i + 1) % 4]);
  const g = new BufferGeometry();
  g.setAttribute("position", new BufferAttribute(new Float32Array(seg), 3));
  return new LineSegments(g, new LineBasicMaterial({ color: FRUSTUM_COLOR }));
}

function boxLines(min, max, color) {
  const size = [0, 1, 2].map((a) => max[a] - min[a]);
  const lines = new LineSegments(new EdgesGeometry(new BoxGeometry(...size)), new LineBasicMaterial({ color }));
  lines.position.set(...[0, 1, 2].map((a) => (min[a] + max[a]) / 2));
  return lines;
}

function egoVehicle() {
  const size = [0, 1, 2].map((a) => EGO.max[a] - EGO.min[a]);
  const g = new Group();
  const body = new Mesh(new BoxGeometry(...size), new MeshBasicMaterial({ color: 0x3a3a3a }));
  body.position.set(...[0, 1, 2].map((a) => (EGO.min[a] + EGO.max[a]) / 2));
  g.add(body, boxLines(EGO.min, EGO.max, 0x000000));
  return g;
}

// One pane: a scene with one grid's surface mesh, the shared ego/frusta/bounds objects, its own label.
class Pane {
  constructor(grid, occ, mask, data, shared) {
    this.name = grid.name;
    this.occ = occ;
    this.mask = mask;
    this.scene = new Scene();
    this.scene.background = new Color(BACKGROUND);
    // one material in an array: the geometry's groups select the rectangles facing the camera (`facing`)
    this.mesh = new Mesh(new BufferGeometry(), [new MeshBasicMaterial({ vertexColors: true })]);
    this.scene.add(this.mesh, egoVehicle(), shared.bounds.clone());
    this.frusta = shared.cameras.map((cam) => { const f = frustumLines(cam); this.scene.add(f); return f; });
    this.counts = classCounts(occ, data.shape, data.free_index, data.classes.length);
  }

  rebuild(data, classOn, showOutside) {
    const s = surface(this.occ, data.shape, data.lower, data.voxel_size, data.free_index, data.colors, classOn,
                      showOutside ? null : this.mask);
    const g = new BufferGeometry();
    g.setAttribute("position", new BufferAttribute(s.positions, 3));
    g.setAttribute("color", new BufferAttribute(s.colors, 3, true));
    g.setIndex(new BufferAttribute(s.indices, 1));
    this.mesh.geometry.dispose();
    this.mesh.geometry = g;
    this.directions = s.directions;
    this.stats = { voxels: s.voxels, faces: s.faces, quads: s.quads };
    return this.stats;
  }

  facing(eye) {
    const g = this.mesh.geometry;
    g.clearGroups();
    let n = 0;
    for (const [start, count] of facingRanges(this.directions, eye)) { g.addGroup(start, count, 0); n += count; }
    return n / 6;
  }
}

export class Viewer {
  // One viewer in `container`: `await Viewer.create(container, data)`; `await viewer.show(data)` replaces what it
  // shows and keeps the WebGL context, its compiled shaders and the camera pose (the server page, result after
  // result).
  static async create(container, data, options = {}) {
    const viewer = new Viewer(container, options);
    await viewer.show(data);
    return viewer;
  }

  constructor(container, options = {}) {
    this.container = container;
    this.renderer = new WebGLRenderer({ antialias: options.antialias ?? false,
                                        preserveDrawingBuffer: !!options.preserveDrawingBuffer });
    this.renderer.outputColorSpace = LinearSRGBColorSpace;  // colours are drawn as given (sRGB bytes)
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.setScissorTest(true);
    this.camera = new PerspectiveCamera(45, 1, 0.1, 500);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(-38, -22, 38);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.target.set(6, 0, 0);
    this.controls.addEventListener("change", () => this.requestRender());
    this.resizer = new ResizeObserver(() => this.resize());
  }

  async show(data) {
    const tStart = performance.now();
    const occs = await Promise.all(data.grids.map((g) => decodeBytes(g.occupancy.data, g.occupancy.encoding)));
    const masks = await Promise.all(data.grids.map((g) => g.mask_camera
      ? decodeBytes(g.mask_camera.data, g.mask_camera.encoding) : null));
    const n = data.shape[0] * data.shape[1] * data.shape[2];
    occs.forEach((o, i) => {
      if (o.length !== n) throw new Error(`grid ${data.grids[i].name}: ${o.length} bytes, expected ${n}`);
    });
    const tDecoded = performance.now();
    // a labels file's mask_camera applies to every pane: what eval scores
    const labelMask = masks.find((m) => m) || null;
    this.data = data;
    this.hasMask = !!labelMask;
    this.classOn = data.classes.map((_, c) => c !== data.free_index);
    this.showOutside = !this.hasMask;
    this.layout = "all";
    for (const p of this.panes || []) p.mesh.geometry.dispose();
    const bounds = boxLines(data.lower, data.lower.map((l, a) => l + data.shape[a] * data.voxel_size), 0xb0b4ba);
    const shared = { bounds, cameras: data.cameras || [] };
    this.panes = data.grids.map((g, i) => new Pane(g, occs[i], masks[i] || labelMask, data, shared));
    this.buildDom();
    this.canvasBox.append(this.renderer.domElement);
    this.resizer.disconnect();
    this.resizer.observe(this.canvasBox);
    this.frames = 0;
    delete this.container.dataset.drawn;
    this.rebuild();
    this.resize();
    this.timings = { start: tStart, decoded: tDecoded, built: performance.now() };
    this.render();                                  // the first frame at once, not at the next animation frame
  }

  buildDom() {
    const d = this.data;
    this.canvasBox = el("div", { class: "occ-canvas" });
    this.labels = el("div", { class: "occ-pane-labels" });
    const legend = el("div", { class: "occ-legend" });
    const header = el("div", { class: "occ-legend-row occ-legend-head" }, el("span", {}, "class"),
      ...this.panes.map((p) => el("span", { class: "occ-count" }, p.name)));
    legend.append(header);
    this.legendBoxes = [];
    d.classes.forEach((name, c) => {
      if (c === d.free_index) return;
      const box = el("input", { type: "checkbox", "data-class": String(c) });
      box.checked = true;
      box.addEventListener("change", () => { this.classOn[c] = box.checked; this.rebuild(); });
      this.legendBoxes.push(box);
      legend.append(el("label", { class: "occ-legend-row" },
        el("span", {}, box, el("i", { class: "occ-swatch", style: `background:${hex(d.colors[c])}` }), name),
        ...this.panes.map((p) => el("span", { class: "occ-count" }, String(p.counts[c])))));
    });
    const controls = el("div", { class: "occ-controls" });
    const all = el("button", { type: "button", onclick: () => this.setAllClasses(true) }, "all");
    const none = el("button", { type: "button", onclick: () => this.setAllClasses(false) }, "none");
    controls.append(el("span", {}, "classes: ", all, " ", none));
    if (this.hasMask) {
      const box = el("input", { type: "checkbox", id: "occ-outside-mask" });
      box.checked = this.showOutside;
      box.addEventListener("change", () => { this.showOutside = box.checked; this.rebuild(); });
      controls.append(el("label", {}, box, " voxels outside mask_camera"));
    }
    if (this.panes.length > 1) {
      const sel = el("select", { id: "occ-layout" }, el("option", { value: "all" }, "side by side"),
        ...this.panes.map((p, i) => el("option", { value: String(i) }, p.name)));
      sel.addEventListener("change", () => { this.layout = sel.value; this.resize(); });
      controls.append(el("label", {}, "show ", sel));
    }
    this.statsLine = el("div", { class: "occ-stats" });
    const side = el("div", { class: "occ-side" }, controls, legend, this.statsLine,
      el("div", { class: "occ-hint" }, "drag: orbit · wheel: zoom · right-drag: pan"));
    const main = el("div", { class: "occ-main" }, this.canvasBox, this.labels);
    const thumbs = this.thumbnails();
    this.container.replaceChildren(el("div", { class: "occ-viewer" }, main, side), ...(thumbs ? [thumbs] : []));
  }

  thumbnails() {
    const cams = (this.data.cameras || []).filter((c) => c.image);
    if (!cams.length) return null;
    // rig layout: front row FL F FR, back row BL B BR (as seen from above, facing forward)
    const order = ["CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT"];
    const byName = Object.fromEntries(cams.map((c) => [c.name, c]));
    const box = el("div", { class: "occ-thumbs" });
    for (const name of [...order.filter((n) => byName[n]), ...cams.map((c) => c.name).filter((n) => !order.includes(n))]) {
      const i = this.data.cameras.findIndex((c) => c.name === name);
      const fig = el("figure", {
        onmouseenter: () => this.highlight(i, true), onmouseleave: () => this.highlight(i, false),
      }, el("img", { src: byName[name].image, alt: name, decoding: "async" }), el("figcaption", {}, name));
      box.append(fig);
    }
    return box;
  }

  highlight(i, on) {
    for (const p of this.panes) p.frusta[i]?.material.color.setHex(on ? FRUSTUM_HOVER : FRUSTUM_COLOR);
    this.requestRender();
  }

  setAllClasses(on) {
    this.classOn = this.classOn.map((_, c) => on && c !== this.data.free_index);
    for (const b of this.legendBoxes) b.checked = on;
    this.rebuild();
  }

  rebuild() {
    const t0 = performance.now();
    const stats = this.panes.map((p) => p.rebuild(this.data, this.classOn, this.showOutside));
    this.lastBuildMs = performance.now() - t0;
    this.statsLine.textContent = this.panes.map((p, i) =>
      `${p.name}: ${stats[i].voxels} voxels shown, ${stats[i].faces} faces on the surface in ${stats[i].quads} rectangles`).join(" · ");
    this.requestRender();
  }

  visiblePanes() {
    return this.layout === "all" ? this.panes : [this.panes[Number(this.layout)]];
  }

  resize() {
    const w = Math.max(1, this.canvasBox.clientWidth), h = Math.max(1, this.canvasBox.clientHeight);
    this.renderer.setSize(w, h, false);
    this.renderer.domElement.style.width = "100%";
    this.renderer.domElement.style.height = "100%";
    const panes = this.visiblePanes();
    this.camera.aspect = w / panes.length / h;
    this.camera.updateProjectionMatrix();
    this.labels.replaceChildren(...panes.map((p) => el("span", { style: `width:${100 / panes.length}%` }, p.name)));
    this.requestRender();
  }

  requestRender() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => { this.pending = false; this.render(); });
  }

  render() {
    const w = this.renderer.domElement.width / this.renderer.getPixelRatio();
    const h = this.renderer.domElement.height / this.renderer.getPixelRatio();
    const panes = this.visiblePanes();
    const pw = Math.floor(w / panes.length);
    panes.forEach((p, i) => {
      this.renderer.setViewport(i * pw, 0, pw, h);
      this.renderer.setScissor(i * pw, 0, pw, h);
      this.drawnQuads = p.facing(this.camera.position.toArray());
      this.renderer.render(p.scene, this.camera);
    });
    this.frames++;
    if (this.frames === 1) {
      // the first frame is finished once its pixels can be read back
      const gl = this.renderer.getContext();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
      this.firstFrameMs = performance.now();
      this.container.dataset.drawn = "1";
      this.container.dispatchEvent(new CustomEvent("occ-drawn", { bubbles: true }));
    }
  }

  // Frames per second while orbiting: the camera circles the target for `seconds`, one step per frame.
  orbitBenchmark(seconds = 3) {
    return new Promise((resolve) => {
      const t0 = performance.now();
      let n = 0;
      const step = () => {
        const angle = 0.02;
        const off = this.camera.position.clone().sub(this.controls.target);
        const x = off.x * Math.cos(angle) - off.y * Math.sin(angle);
        off.y = off.x * Math.sin(angle) + off.y * Math.cos(angle);
        off.x = x;
        this.camera.position.copy(this.controls.target).add(off);
        this.camera.lookAt(this.controls.target);
        this.render();
        n++;
        const dt = performance.now() - t0;
        if (dt < seconds * 1000) requestAnimationFrame(step);
        else resolve({ frames: n, seconds: dt / 1000, fps: n / (dt / 1000) });
      };
      requestAnimationFrame(step);
    });
  }

  state() {
    return {
      drawn: this.container.dataset.drawn === "1", firstFrameMs: this.firstFrameMs, buildMs: this.lastBuildMs,
      timings: this.timings,
      panes: this.panes.map((p) => ({ name: p.name, ...p.stats })), layout: this.layout, drawnQuads: this.drawnQuads,
    };
  }
}
