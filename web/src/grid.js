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

// The surface of the shown voxels of one grid: the faces between a shown voxel and a voxel not shown (or the grid's
// border), with coplanar neighbouring faces of one class merged into rectangles (greedy meshing: the same picture,
// since faces are flat-coloured, with a fraction of the triangles). `shown(v, cls)` decides per voxel. Returns
// positions (metres), colours (uint8 RGB, shaded by direction), triangle indices (counter-clockwise seen from
// outside), and the counts: voxels shown, voxel faces on the surface, rectangles drawn.
export function surface(occ, shape, lower, voxel, free, colors, shown) {
  const S = [shape[1] * shape[2], shape[2], 1];
  const vis = new Uint8Array(occ.length);            // class + 1 of each shown voxel, 0 elsewhere
  let nShown = 0;
  for (let v = 0; v < occ.length; v++) {
    const c = occ[v];
    if (c !== free && shown(v, c)) { vis[v] = c + 1; nShown++; }
  }
  const quads = [];                                   // flat: d, plane, u0, v0, u1, v1, class
  let nFaces = 0;
  for (let a = 0; a < 3; a++) {
    const u = (a + 1) % 3, w = (a + 2) % 3;           // (a, u, w) cyclic: e_u × e_w = e_a
    const A = shape[a], U = shape[u], W = shape[w];
    const mask = new Uint8Array(U * W);
    for (const sign of [1, -1]) {
      const d = 2 * a + (sign > 0 ? 0 : 1);
      for (let s = 0; s < A; s++) {
        const next = s + sign, edge = next < 0 || next >= A;
        for (let i = 0; i < U; i++) for (let j = 0; j < W; j++) {
          const v = s * S[a] + i * S[u] + j * S[w];
          const c = vis[v];
          const open = c && (edge || !vis[v + sign * S[a]]);
          mask[i * W + j] = open ? c : 0;
          if (open) nFaces++;
        }
        for (let i = 0; i < U; i++) for (let j = 0; j < W;) {
          const c = mask[i * W + j];
          if (!c) { j++; continue; }
          let len = 1;
          while (j + len < W && mask[i * W + j + len] === c) len++;
          let rows = 1;
          grow: for (; i + rows < U; rows++) {
            for (let k = 0; k < len; k++) if (mask[(i + rows) * W + j + k] !== c) break grow;
          }
          for (let r = 0; r < rows; r++) mask.fill(0, (i + r) * W + j, (i + r) * W + j + len);
          quads.push(d, s + (sign > 0 ? 1 : 0), i, j, i + rows, j + len, c - 1);
          j += len;
        }
      }
    }
  }
  const n = quads.length / 7;
  const pos = new Float32Array(n * 12), col = new Uint8Array(n * 12), idx = new Uint32Array(n * 6);
  for (let q = 0; q < n; q++) {
    const [d, plane, u0, w0, u1, w1, c] = quads.slice(q * 7, q * 7 + 7);
    const a = d >> 1, u = (a + 1) % 3, w = (a + 2) % 3;
    const corners = [[u0, w0], [u1, w0], [u1, w1], [u0, w1]];
    if (d & 1) corners.reverse();                     // facing -a: the other winding
    const rgb = colors[c];
    corners.forEach(([cu, cw], k) => {
      const o = q * 12 + k * 3;
      pos[o + a] = lower[a] + plane * voxel;
      pos[o + u] = lower[u] + cu * voxel;
      pos[o + w] = lower[w] + cw * voxel;
      for (let ch = 0; ch < 3; ch++) col[o + ch] = Math.round(rgb[ch] * SHADE[d]);
    });
    const b = q * 4, t = q * 6;
    idx[t] = b; idx[t + 1] = b + 1; idx[t + 2] = b + 2; idx[t + 3] = b; idx[t + 4] = b + 2; idx[t + 5] = b + 3;
  }
  return { positions: pos, colors: col, indices: idx, voxels: nShown, faces: nFaces, quads: n };
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
