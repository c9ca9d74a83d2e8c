// Grids as the viewer receives them, and the surface of their occupied voxels.
//
// A grid is uint8 [X, Y, Z] in C order ([x, y, z] of the ego frame: x forward, y left, z up), voxel
// (i, j, k) at flat index (i * Y + j) * Z + k, spanning lower + index * voxel .. lower + (index + 1) * voxel
// metres; the value is a class index, `free` for free space (docs/contracts.md).

// base64 → Uint8Array; "zlib-base64" data is inflated with the browser's DecompressionStream (no library);
// "bytes": already a Uint8Array.
export async function decodeBytes(text, encoding) {
  if (encoding === "bytes") return text;
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

// The surface of the shown voxels of one grid: the faces between a shown voxel and a voxel not shown (or the grid's
// border), with coplanar neighbouring faces of one class merged into rectangles (greedy meshing: the same picture,
// since faces are flat-coloured, with a fraction of the triangles). A voxel is shown when its class is on in
// `classOn` and, given a `mask` (mask_camera), inside it. Work ∝ voxels (one pass) + shown voxels. Returns
// positions (metres), colours (uint8 RGB, shaded by direction), triangle indices (counter-clockwise seen from
// outside), the counts (voxels shown, voxel faces on the surface, rectangles), and `directions`: per face
// direction, the coordinate of each plane and where its rectangles start (see `facingRanges`).
export function surface(occ, shape, lower, voxel, free, colors, classOn, mask = null) {
  const [X, Y, Z] = shape;
  const S = [Y * Z, Z, 1];
  const vis = new Uint8Array(occ.length);            // class + 1 of each shown voxel, 0 elsewhere
  const list = new Int32Array(occ.length);           // the shown voxels, in index order, and their coordinates
  const cx = new Int16Array(occ.length), cy = new Int16Array(occ.length), cz = new Int16Array(occ.length);
  let nShown = 0;
  for (let i = 0, v = 0; i < X; i++) for (let j = 0; j < Y; j++) for (let k = 0; k < Z; k++, v++) {
    const c = occ[v];
    if (c === free || !classOn[c] || (mask !== null && mask[v] === 0)) continue;
    vis[v] = c + 1;
    list[nShown] = v; cx[nShown] = i; cy[nShown] = j; cz[nShown] = k;
    nShown++;
  }
  const coords = [cx, cy, cz];
  let quads = new Int16Array(7 * 4096), nq = 0;        // flat: d, plane, u0, w0, u1, w1, class
  const directions = [];                              // per direction: its planes, in buffer order
  let nFaces = 0;
  for (let a = 0; a < 3; a++) {
    const u = (a + 1) % 3, w = (a + 2) % 3;           // (a, u, w) cyclic: e_u × e_w = e_a
    const A = shape[a], W = shape[w], ca = coords[a], cu = coords[u], cw = coords[w];
    // the shown voxels (their positions in `list`) bucketed by their coordinate along a (counting sort)
    const start = new Int32Array(A + 1);
    for (let n = 0; n < nShown; n++) start[ca[n] + 1]++;
    for (let s = 0; s < A; s++) start[s + 1] += start[s];
    const bucket = new Int32Array(nShown), fill = start.slice(0, A);
    for (let n = 0; n < nShown; n++) bucket[fill[ca[n]]++] = n;
    const plane = new Uint8Array(shape[u] * W);     // this slice's open faces: class + 1
    const first = new Int16Array(shape[u]).fill(W), last = new Int16Array(shape[u]).fill(-1);  // per row
    for (const sign of [1, -1]) {
      const d = 2 * a + (sign > 0 ? 0 : 1);
      const slices = { d, axis: a, sign, at: new Float32Array(A), start: new Int32Array(A + 1) };
      directions.push(slices);
      for (let s = 0; s < A; s++) {
        slices.at[s] = lower[a] + (s + (sign > 0 ? 1 : 0)) * voxel;
        slices.start[s] = nq / 7;
        const edge = s + sign < 0 || s + sign >= A;
        let lo = Infinity, hi = -1;
        for (let b = start[s]; b < start[s + 1]; b++) {
          const n = bucket[b], v = list[n];
          if (!edge && vis[v + sign * S[a]]) continue;
          const i = cu[n], j = cw[n];
          plane[i * W + j] = vis[v];
          if (j < first[i]) first[i] = j;
          if (j > last[i]) last[i] = j;
          nFaces++;
          if (i < lo) lo = i;
          if (i > hi) hi = i;
        }
        for (let i = lo; i <= hi; i++) for (let j = first[i], end = last[i] + 1; j < end;) {
          const c = plane[i * W + j];
          if (!c) { j++; continue; }
          let len = 1;
          while (j + len < W && plane[i * W + j + len] === c) len++;
          let rows = 1;
          grow: for (; i + rows <= hi; rows++) {
            for (let k = 0; k < len; k++) if (plane[(i + rows) * W + j + k] !== c) break grow;
          }
          for (let r = 0; r < rows; r++) plane.fill(0, (i + r) * W + j, (i + r) * W + j + len);
          if (nq + 7 > quads.length) { const grown = new Int16Array(quads.length * 2); grown.set(quads); quads = grown; }
          quads[nq] = d; quads[nq + 1] = s + (sign > 0 ? 1 : 0); quads[nq + 2] = i; quads[nq + 3] = j;
          quads[nq + 4] = i + rows; quads[nq + 5] = j + len; quads[nq + 6] = c - 1;
          nq += 7;
          j += len;
        }
        for (let i = lo; i <= hi; i++) { first[i] = W; last[i] = -1; }
      }
      slices.start[A] = nq / 7;
    }
  }
  const n = nq / 7;
  const pos = new Float32Array(n * 12), col = new Uint8Array(n * 12), idx = new Uint32Array(n * 6);
  const shade = new Float32Array(SHADE);
  for (let q = 0; q < n; q++) {
    const o7 = q * 7, d = quads[o7], a = d >> 1, u = (a + 1) % 3, w = (a + 2) % 3;
    const at = lower[a] + quads[o7 + 1] * voxel;
    const u0 = lower[u] + quads[o7 + 2] * voxel, w0 = lower[w] + quads[o7 + 3] * voxel;
    const u1 = lower[u] + quads[o7 + 4] * voxel, w1 = lower[w] + quads[o7 + 5] * voxel;
    const rgb = colors[quads[o7 + 6]], f = shade[d];
    const r = Math.round(rgb[0] * f), g = Math.round(rgb[1] * f), bl = Math.round(rgb[2] * f);
    const flip = d & 1;                               // facing -a: the other winding
    for (let k = 0; k < 4; k++) {
      const kk = flip ? 3 - k : k;                    // corners (u0,w0) (u1,w0) (u1,w1) (u0,w1)
      const o = q * 12 + k * 3;
      pos[o + a] = at;
      pos[o + u] = kk === 1 || kk === 2 ? u1 : u0;
      pos[o + w] = kk >= 2 ? w1 : w0;
      col[o] = r; col[o + 1] = g; col[o + 2] = bl;
    }
    const b = q * 4, t = q * 6;
    idx[t] = b; idx[t + 1] = b + 1; idx[t + 2] = b + 2; idx[t + 3] = b; idx[t + 4] = b + 2; idx[t + 5] = b + 3;
  }
  return { positions: pos, colors: col, indices: idx, voxels: nShown, faces: nFaces, quads: n, directions };
}

// The index ranges (start, count, in indices) of the rectangles that can face a camera at `eye`: a plane of
// +x faces at x = p is seen only from x > p, and so on, so per direction one contiguous run of planes is drawn —
// exactly what back-face culling would keep, without sending the rest through the (software) rasteriser.
export function facingRanges(directions, eye) {
  const out = [];
  for (const s of directions) {
    const A = s.at.length, e = eye[s.axis];
    let lo = 0, hi = A;                                // planes lo..hi-1 face the eye
    if (s.sign > 0) { while (hi > 0 && !(s.at[hi - 1] < e)) hi--; } else { while (lo < A && !(s.at[lo] > e)) lo++; }
    const a = s.start[lo], b = s.start[hi];
    if (b > a) {
      const prev = out[out.length - 1];
      if (prev && prev[0] + prev[1] === a * 6) prev[1] += (b - a) * 6;
      else out.push([a * 6, (b - a) * 6]);
    }
  }
  return out;
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
