// Grids as the viewer receives them, and the surface of their occupied voxels.
//
// A grid is uint8 [X, Y, Z] in C order ([x, y, z] of the ego frame: x forward, y left, z up), voxel
// (i, j, k) at flat index (i * Y + j) * Z + k, spanning lower + index * voxel .. lower + (index + 1) * voxel
// metres; the value is a class index, `free` for free space (docs/contracts.md).

// base64 → Uint8Array; "zlib-base64" data is inflated with the browser's DecompressionStream (no library).
export async function decodeBytes(text, encoding) {
  const bin = atob(text);
  const raw = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) raw[i] = bin.charCodeAt(i);
  if (encoding === "base64") return raw;
  if (encoding !== "zlib-base64") throw new Error(`unknown encoding ${encoding}`);
  const stream = new Blob([raw]).stream().pipeThrough(new DecompressionStream("deflate"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

// Per class: voxel count, and columns whose highest occupied voxel has that class (what a top-down view shows).
export function classCounts(occ, shape, free, nClasses) {
  const counts = new Array(nClasses).fill(0);
  for (let i = 0; i < occ.length; i++) if (occ[i] !== free && occ[i] < nClasses) counts[occ[i]]++;
  return counts;
}

// Face shading by direction (+x, -x, +y, -y, +z, -z): tops keep the class colour exactly, sides are darker, so
// cubes read as cubes without lights (and a screenshot can be checked against the class colours).
const SHADE = [0.80, 0.80, 0.66, 0.66, 1.0, 0.5];
// For each direction: the unit step and the four corners of the face, as offsets of the voxel's lower corner.
const FACES = [
  [[1, 0, 0], [[1, 0, 0], [1, 1, 0], [1, 1, 1], [1, 0, 1]]],
  [[-1, 0, 0], [[0, 0, 0], [0, 0, 1], [0, 1, 1], [0, 1, 0]]],
  [[0, 1, 0], [[0, 1, 0], [0, 1, 1], [1, 1, 1], [1, 1, 0]]],
  [[0, -1, 0], [[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]]],
  [[0, 0, 1], [[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]],
  [[0, 0, -1], [[0, 0, 0], [0, 1, 0], [1, 1, 0], [1, 0, 0]]],
];

// The faces between shown and not-shown voxels (or the grid's border) of one grid: positions (metres), colours
// (uint8 RGB, shaded by direction) and triangle indices, ready for a BufferGeometry. `shown(v, cls)` decides per
// voxel; each shown voxel is visited once, each of its six neighbours looked up once.
export function surface(occ, shape, lower, voxel, free, colors, shown) {
  const [X, Y, Z] = shape;
  const strides = [Y * Z, Z, 1];
  const vis = new Uint8Array(occ.length);
  let nShown = 0;
  for (let v = 0; v < occ.length; v++) {
    const c = occ[v];
    if (c !== free && shown(v, c)) { vis[v] = 1; nShown++; }
  }
  const exposed = (v, i, j, k, d) => {
    const [dx, dy, dz] = FACES[d][0];
    const a = i + dx, b = j + dy, c = k + dz;
    if (a < 0 || b < 0 || c < 0 || a >= X || b >= Y || c >= Z) return true;
    return !vis[v + dx * strides[0] + dy * strides[1] + dz * strides[2]];
  };
  let nFaces = 0;
  for (let i = 0, v = 0; i < X; i++) for (let j = 0; j < Y; j++) for (let k = 0; k < Z; k++, v++) {
    if (!vis[v]) continue;
    for (let d = 0; d < 6; d++) if (exposed(v, i, j, k, d)) nFaces++;
  }
  const pos = new Float32Array(nFaces * 12);
  const col = new Uint8Array(nFaces * 12);
  const idx = new Uint32Array(nFaces * 6);
  let f = 0;
  for (let i = 0, v = 0; i < X; i++) for (let j = 0; j < Y; j++) for (let k = 0; k < Z; k++, v++) {
    if (!vis[v]) continue;
    const rgb = colors[occ[v]];
    for (let d = 0; d < 6; d++) {
      if (!exposed(v, i, j, k, d)) continue;
      const corners = FACES[d][1];
      for (let q = 0; q < 4; q++) {
        const o = f * 12 + q * 3;
        pos[o] = lower[0] + (i + corners[q][0]) * voxel;
        pos[o + 1] = lower[1] + (j + corners[q][1]) * voxel;
        pos[o + 2] = lower[2] + (k + corners[q][2]) * voxel;
        for (let ch = 0; ch < 3; ch++) col[o + ch] = Math.round(rgb[ch] * SHADE[d]);
      }
      const base = f * 4, t = f * 6;
      idx[t] = base; idx[t + 1] = base + 1; idx[t + 2] = base + 2;
      idx[t + 3] = base; idx[t + 4] = base + 2; idx[t + 5] = base + 3;
      f++;
    }
  }
  return { positions: pos, colors: col, indices: idx, voxels: nShown, faces: nFaces };
}

// The top-down picture of a grid, the rule of occflownet/pictures.py `top_down` (and the server's image/png):
// each (x, y) column takes the colour of its highest non-free voxel, empty columns colors[free]; image up = +x,
// image left = +y; the ego vehicle a black 2·scale square at the centre. Returns RGBA bytes and the size.
export function topDown(occ, shape, colors, free, scale = 2) {
  const [X, Y, Z] = shape;
  const H = X * scale, W = Y * scale;
  const out = new Uint8ClampedArray(H * W * 4);
  for (let i = 0; i < X; i++) for (let j = 0; j < Y; j++) {
    let cls = free;
    for (let k = Z - 1; k >= 0; k--) {
      const c = occ[(i * Y + j) * Z + k];
      if (c !== free) { cls = c; break; }
    }
    const rgb = colors[cls];
    const r0 = (X - 1 - i) * scale, c0 = (Y - 1 - j) * scale;
    for (let r = r0; r < r0 + scale; r++) for (let c = c0; c < c0 + scale; c++) {
      const o = (r * W + c) * 4;
      out[o] = rgb[0]; out[o + 1] = rgb[1]; out[o + 2] = rgb[2]; out[o + 3] = 255;
    }
  }
  const cr = Math.floor(H / 2), cc = Math.floor(W / 2);
  for (let r = cr - scale; r < cr + scale; r++) for (let c = cc - scale; c < cc + scale; c++) {
    const o = (r * W + c) * 4;
    out[o] = 0; out[o + 1] = 0; out[o + 2] = 0; out[o + 3] = 255;
  }
  return { rgba: out, width: W, height: H };
}
