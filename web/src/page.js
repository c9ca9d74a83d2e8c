// The server page (GET /ui): pick six camera images (and optionally a calibration JSON), send them to
// POST /v1/occupancy exactly as any client would, then show the top-down picture and the 3D view of the answer
// with the latencies. Errors are the API's own {"error": {"code", "message"}}, shown as they come. Everything
// is fetched from this server only (the page's Content-Security-Policy says so too).
import { decodeBytes, topDown } from "./grid.js";
import { Viewer } from "./viewer.js";

const $ = (id) => document.getElementById(id);

// A file's camera: its name without extension if that is a camera name, else the longest camera name it contains.
export function cameraOf(fileName, cameras) {
  const stem = fileName.replace(/\.[^.]*$/, "").toUpperCase();
  if (cameras.includes(stem)) return stem;
  const hits = cameras.filter((c) => stem.includes(c)).sort((a, b) => b.length - a.length);
  return hits[0] || null;
}

function headers(extra = {}) {
  const key = $("api-key").value.trim();
  return key ? { ...extra, Authorization: `Bearer ${key}` } : extra;
}

// The API's error body as one line; anything else (no JSON) as the status line and the start of the body.
async function errorText(response) {
  const text = await response.text();
  try {
    const e = JSON.parse(text).error;
    if (e && e.code) return `HTTP ${response.status} ${e.code}: ${e.message}`;
  } catch (_) { /* not the API's error shape */ }
  return `HTTP ${response.status} ${response.statusText}: ${text.slice(0, 300)}`;
}

// (w, h) from a JPEG's SOF or a PNG's IHDR header, read from the first 256 kB of the file; null if not found.
// Cheaper than decoding the image, which would take CPU from the server while it computes.
export async function imageSize(file) {
  const b = new Uint8Array(await file.slice(0, 262144).arrayBuffer());
  const u16 = (i) => (b[i] << 8) | b[i + 1];
  if (b[0] === 0x89 && b[1] === 0x50 && b.length >= 24) {
    const u32 = (i) => ((b[i] << 24) | (b[i + 1] << 16) | (b[i + 2] << 8) | b[i + 3]) >>> 0;
    return [u32(16), u32(20)];
  }
  if (b[0] !== 0xff || b[1] !== 0xd8) return null;
  for (let i = 2; i + 9 < b.length;) {
    if (b[i] !== 0xff) { i++; continue; }
    const m = b[i + 1];
    if (m === 0xd8 || m === 0x01 || (m >= 0xd0 && m <= 0xd7) || m === 0xff) { i += m === 0xff ? 1 : 2; continue; }
    if (m >= 0xc0 && m <= 0xcf && m !== 0xc4 && m !== 0xc8 && m !== 0xcc) return [u16(i + 7), u16(i + 5)];
    i += 2 + u16(i + 2);
  }
  return null;
}

class Page {
  constructor() {
    this.files = {};          // camera → File
    this.calibration = null;  // File
    this.metadata = null;
    this.viewer = null;
    this.last = null;         // what the last request gave: the test and a curious user read it
    $("images").addEventListener("change", (e) => this.addImages([...e.target.files]));
    $("calibration").addEventListener("change", (e) => { this.calibration = e.target.files[0] || null; this.show(); });
    $("run").addEventListener("click", () => this.run());
    $("api-key").addEventListener("change", () => this.loadMetadata());
    const drop = $("drop");
    drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
    drop.addEventListener("dragleave", () => drop.classList.remove("over"));
    drop.addEventListener("drop", (e) => {
      e.preventDefault();
      drop.classList.remove("over");
      const files = [...e.dataTransfer.files];
      const calib = files.find((f) => /\.json$/i.test(f.name));
      if (calib) this.calibration = calib;
      this.addImages(files.filter((f) => f !== calib));
    });
    this.loadMetadata();
  }

  async loadMetadata() {
    const r = await fetch("/v1/metadata", { headers: headers() }).catch((e) => e);
    if (!(r instanceof Response)) return this.error(`could not reach the server: ${r}`);
    if (!r.ok) return this.error(await errorText(r) + (r.status === 401 ? " (enter the API key above)" : ""));
    this.metadata = await r.json();
    const m = this.metadata.model, lim = this.metadata.limits;
    $("model").textContent = `${m.file} (preset ${m.preset}, occflownet ${m.occflownet_version}); limits: body ` +
      `${(lim.max_body_bytes / 2 ** 20).toFixed(0)} MiB, ${lim.max_image_pixels} pixels per image`;
    this.error(null);
    this.show();
  }

  addImages(files) {
    const cams = this.metadata ? this.metadata.cameras : [];
    this.unmatched = [];
    this.files = {};
    for (const f of files) {
      const cam = cameraOf(f.name, cams);
      if (cam) this.files[cam] = f; else this.unmatched.push(f.name);
    }
    this.show();
  }

  show() {
    const cams = this.metadata ? this.metadata.cameras : [];
    const rows = cams.map((c) => {
      const f = this.files[c];
      const tr = document.createElement("tr");
      tr.innerHTML = "<td></td><td></td>";
      tr.children[0].textContent = c;
      tr.children[1].textContent = f ? `${f.name} (${(f.size / 1024).toFixed(0)} kB)` : "no image";
      if (!f) tr.children[1].className = "missing";
      return tr;
    });
    $("assign").replaceChildren(...rows);
    const notes = [];
    if (this.unmatched?.length) notes.push(`not sent (the name contains no camera name): ${this.unmatched.join(", ")}`);
    notes.push(this.calibration ? `calibration: ${this.calibration.name}` : "no calibration: the model's default");
    $("notes").textContent = notes.join(" · ");
  }

  error(text) {
    const box = $("error");
    box.hidden = !text;
    box.textContent = text || "";
    if (text) $("result").hidden = true;            // never an earlier answer under a new error
  }

  async run() {
    if (!this.metadata) await this.loadMetadata();
    if (!this.metadata) return;
    const form = new FormData();
    for (const cam of this.metadata.cameras) if (this.files[cam]) form.append(cam, this.files[cam], this.files[cam].name);
    if (this.calibration) form.append("calibration", this.calibration, this.calibration.name);
    this.error(null);
    $("run").disabled = true;
    $("latency").textContent = "waiting for the server…";
    const t0 = performance.now();
    // the frusta and thumbnails are prepared while the server computes
    const cameras = this.cameras();
    try {
      const r = await fetch("/v1/occupancy", { method: "POST", body: form, headers: headers({ Accept: "application/json" }) });
      if (!r.ok) {
        const text = await errorText(r);
        this.last = { ok: false, status: r.status, message: text };
        $("latency").textContent = "";
        return this.error(text);
      }
      const tHeaders = performance.now();
      const body = await r.json();
      const tFetch = performance.now();
      // the answer on screen first (top-down picture, latencies), then the 3D view
      const occ = await decodeBytes(body.occupancy_base64, "base64");
      $("result").hidden = false;
      this.drawTopDown(occ, body);
      const s = body.timings_ms;
      const line = `server: ${s.total.toFixed(0)} ms (queue ${s.queue.toFixed(0)}, decode ${s.decode.toFixed(0)}, ` +
        `inference ${s.inference.toFixed(0)}, encode ${s.encode.toFixed(1)}) · round trip in the browser: ` +
        `${(tFetch - t0).toFixed(0)} ms to the answer`;
      $("latency").textContent = line + ", drawing it in 3D…";
      const tShown = performance.now();
      await this.draw3d(occ, body, cameras);
      const tDrawn = performance.now();
      $("latency").textContent = line + `, ${(tShown - t0).toFixed(0)} ms to the top-down picture, ` +
        `${(tDrawn - t0).toFixed(0)} ms to the 3D view`;
      this.last = { ok: true, status: r.status, headersMs: tHeaders - t0, fetchMs: tFetch - t0,
                    shownMs: tShown - t0, drawnMs: tDrawn - t0, viewer: this.viewer.state(),
                    server: body.timings_ms, serverTiming: r.headers.get("Server-Timing"),
                    classCounts: body.class_counts };
    } catch (e) {
      this.last = { ok: false, status: 0, message: String(e) };
      $("latency").textContent = "";
      this.error(`could not reach the server: ${e}`);
    } finally {
      $("run").disabled = false;
    }
  }

  async cameras() {
    // frusta from the request's calibration (or the model's default); intrinsics for the image as sent
    let calib = this.metadata.default_calibration;
    if (this.calibration) {
      try { calib = JSON.parse(await this.calibration.text()); } catch (_) { /* the server said it was fine */ }
    }
    const out = [];
    for (const name of this.metadata.cameras) {
      const c = calib.cameras?.[name];
      if (!c) continue;
      const file = this.files[name];
      if (this.urls?.[name]) URL.revokeObjectURL(this.urls[name]);
      const image = file ? URL.createObjectURL(file) : null;
      (this.urls ||= {})[name] = image;
      // intrinsics are for the camera's image_size, the top-level one, or the image as sent (docs/contracts.md)
      const size = c.image_size || calib.image_size || (file ? await imageSize(file) : null);
      if (size) out.push({ name, intrinsic: c.intrinsic, cam2ego: c.cam2ego, image_size: size, image });
    }
    return out;
  }

  drawTopDown(occ, body) {
    const td = topDown(occ, body.shape, this.metadata.class_colors, body.free_index, 2);
    const canvas = $("top-down");
    canvas.width = td.width;
    canvas.height = td.height;
    canvas.getContext("2d").putImageData(new ImageData(td.rgba, td.width, td.height), 0, 0);
  }

  async draw3d(occ, body, cameras) {
    const data = {
      title: "answer", shape: body.shape, lower: body.grid.lower, voxel_size: body.grid.voxel_size,
      free_index: body.free_index, classes: body.classes, colors: this.metadata.class_colors,
      grids: [{ name: "answer", occupancy: { data: occ, encoding: "bytes" } }],
      cameras: await cameras,
    };
    const box = $("view3d");
    const drawn = new Promise((resolve) => box.addEventListener("occ-drawn", resolve, { once: true }));
    if (this.viewer) await this.viewer.show(data);
    else this.viewer = await Viewer.create(box, data);
    await drawn;
  }
}

export function startPage() {
  window.occPage = new Page();
  return window.occPage;
}
