"""The 3D viewer's figures (docs/results.md#viewing): size, time to the first frame and frame rate while orbiting
of a viewer file in headless Chromium (SwiftShader WebGL, the browser tests' flags), for a grid of 60,000 occupied
voxels, and the same for the plotly alternatives the choice was made against (when plotly is installed:
``pip install plotly``; it is no dependency of the project).

    python -m benchmarks.perf.bench_viewer [--voxels 60000] [--runs 3] [--out DIR] [--no-plotly] [--jsonl PATH]

The 60,000-voxel grid is the real Occ3D sample (../shared/data/occ3d-sample/labels.npz, 39,092 occupied voxels)
with columns under its vegetation and buildings filled towards the ground until the count is reached (a denser
street than the sample, like a prediction that fills what it cannot see). Per run, a fresh browser: "open" is
from ``driver.get`` to the viewer's drawn flag (wall clock), "first frame" the page's own time from navigation
start to its first frame read back; fps = frames drawn while the camera circles the scene for 3 s. Prints a markdown
table, one row per viewer (medians over the runs) with the load average and the float32 matmul rate (appended to
``--jsonl``).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import SHARED_DATA, Results, add_jsonl_option
from occflownet.occ3d import CLASS_COLORS, FREE, GRID, MANMADE, VEGETATION
from occflownet.viewer import ViewGrid, read_grid, write_viewer
from tests.browser import browser, setup_browser, wait_for

LABELS = SHARED_DATA / "occ3d-sample" / "labels.npz"


def dense_grid(n: int) -> np.ndarray:
    """The real sample with columns under vegetation/manmade filled downwards until ``n`` voxels are occupied."""
    occ = read_grid(LABELS).occupancy.copy()
    for k in range(GRID.shape[2] - 2, -1, -1):
        need = n - int((occ != FREE).sum())
        if need <= 0:
            break
        fill = np.flatnonzero((occ[:, :, k] == FREE) & np.isin(occ[:, :, k + 1], (MANMADE, VEGETATION)))[:need]
        layer = occ[:, :, k].reshape(-1)
        layer[fill] = occ[:, :, k + 1].reshape(-1)[fill]
        occ[:, :, k] = layer.reshape(GRID.shape[:2])
    if int((occ != FREE).sum()) != n:
        raise SystemExit(f"could not make a grid of {n} occupied voxels")
    return occ


def measure_three(path: Path, runs: int) -> dict:
    opens, frames, fps = [], [], []
    for _ in range(runs):
        with browser() as d:
            t0 = time.perf_counter()
            d.get(path.as_uri())
            state = wait_for(d, "window.occViewer && window.occViewer.state().drawn && window.occViewer.state()")
            opens.append(time.perf_counter() - t0)
            frames.append(state["firstFrameMs"] / 1e3)
            orbit = d.execute_async_script("const done = arguments[arguments.length - 1];"
                                           "window.occViewer.orbitBenchmark(3).then(done);")
            fps.append(orbit["fps"])
    pane = state["panes"][0]
    return {"open_s": opens, "first_frame_s": frames, "fps": fps, "faces": f"{pane['faces']} faces in {pane['quads']} rectangles"}


def plotly_files(occ: np.ndarray, folder: Path) -> dict[str, Path]:
    """The two plotly variants: one Scatter3d of square markers per voxel, and a Mesh3d of the exposed faces."""
    import plotly.graph_objects as go

    idx = np.argwhere(occ != FREE)
    centres = np.asarray(GRID.lower) + (idx + 0.5) * GRID.voxel_size
    cls = occ[tuple(idx.T)]
    rgb = [f"rgb({r},{g},{b})" for r, g, b in CLASS_COLORS[cls]]
    post = "document.body.dataset.drawn = performance.now();"
    scatter = go.Figure(go.Scatter3d(x=centres[:, 0], y=centres[:, 1], z=centres[:, 2], mode="markers",
                                     marker={"symbol": "square", "size": 2, "color": rgb}))
    scatter.update_layout(scene={"aspectmode": "data"}, margin={"l": 0, "r": 0, "t": 0, "b": 0})
    out = {"plotly Scatter3d (markers)": folder / "plotly_scatter.html"}
    scatter.write_html(out["plotly Scatter3d (markers)"], include_plotlyjs=True, post_script=post)
    verts, faces, colors = _exposed_faces(occ)
    mesh = go.Figure(go.Mesh3d(x=verts[:, 0], y=verts[:, 1], z=verts[:, 2], i=faces[:, 0], j=faces[:, 1],
                               k=faces[:, 2], facecolor=colors, flatshading=True))
    mesh.update_layout(scene={"aspectmode": "data"}, margin={"l": 0, "r": 0, "t": 0, "b": 0})
    out["plotly Mesh3d (exposed faces)"] = folder / "plotly_mesh.html"
    mesh.write_html(out["plotly Mesh3d (exposed faces)"], include_plotlyjs=True, post_script=post)
    return out


def _exposed_faces(occ: np.ndarray):
    """Vertices, triangles and per-triangle colours of the faces between occupied and free voxels (numpy)."""
    occupied = np.pad(occ != FREE, 1)
    corners = {0: [(1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1)], 1: [(0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0)],
               2: [(0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]}
    verts, tris, cols, base = [], [], [], 0
    for axis in range(3):
        for sign in (1, -1):
            shift = np.roll(occupied, -sign, axis=axis)
            idx = np.argwhere(occupied & ~shift) - 1
            idx = idx[(idx >= 0).all(1) & (idx < np.asarray(occ.shape)).all(1)]
            quad = np.asarray(corners[axis], float)
            if sign < 0:
                quad[:, axis] = 0
            v = (np.asarray(GRID.lower) + (idx[:, None, :] + quad[None]) * GRID.voxel_size).reshape(-1, 3)
            q = base + 4 * np.arange(len(idx))[:, None]
            tris.append(np.concatenate([q + [0, 1, 2], q + [0, 2, 3]]))
            rgb = CLASS_COLORS[occ[tuple(idx.T)]]
            cols += [f"rgb({r},{g},{b})" for r, g, b in np.concatenate([rgb, rgb])]
            verts.append(v)
            base += len(v)
    return np.concatenate(verts), np.concatenate(tris), cols


def measure_plotly(path: Path, runs: int) -> dict:
    opens, frames, fps = [], [], []
    for _ in range(runs):
        with browser() as d:
            t0 = time.perf_counter()
            d.get(path.as_uri())
            drawn = wait_for(d, "document.body.dataset.drawn", timeout=120)
            opens.append(time.perf_counter() - t0)
            frames.append(float(drawn) / 1e3)
            fps.append(d.execute_async_script(
                "const done = arguments[arguments.length - 1]; const gd = document.querySelector('.plotly-graph-div');"
                "const t0 = performance.now(); let n = 0;"
                "const step = () => { const a = n * 0.02; Plotly.relayout(gd, {'scene.camera.eye': "
                "{x: 1.5 * Math.cos(a), y: 1.5 * Math.sin(a), z: 1.2}}).then(() => { n++;"
                "  if (performance.now() - t0 < 3000) requestAnimationFrame(step);"
                "  else done(n / ((performance.now() - t0) / 1000)); }); };"
                "requestAnimationFrame(step);"))
    return {"open_s": opens, "first_frame_s": frames, "fps": fps}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--voxels", type=int, default=60000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="keep the files here (default: a temporary folder)")
    ap.add_argument("--no-plotly", action="store_true")
    add_jsonl_option(ap)
    args = ap.parse_args()
    results = Results("bench_viewer", args.jsonl)
    setup_browser()
    folder = args.out or Path(tempfile.mkdtemp(prefix="occflownet-bench-viewer-"))
    occ = dense_grid(args.voxels)
    files = {"three.js (this viewer)": write_viewer(folder / "viewer.html", [ViewGrid("dense", occ)],
                                                    title=f"{args.voxels} occupied voxels")}
    if not args.no_plotly:
        try:
            files.update(plotly_files(occ, folder))
        except ImportError:
            print("plotly not installed: only the three.js viewer is measured", file=sys.stderr)
    print(f"{args.voxels} occupied voxels, {args.runs} runs each, fresh browser per run; files in {folder}")
    print("| viewer | file size | open (get → drawn) | first frame (in page) | fps orbiting | machine |")
    print("|---|---:|---:|---:|---:|---|")
    for name, path in files.items():
        m = measure_three(path, args.runs) if path.name == "viewer.html" else measure_plotly(path, args.runs)
        med = {k: statistics.median(v) for k, v in m.items() if isinstance(v, list)}
        extra = f" ({m['faces']} faces)" if "faces" in m else ""
        results.add({"viewer": name, "voxels": args.voxels, "bytes": path.stat().st_size, **m},
                    f"| {name}{extra} | {path.stat().st_size / 2**20:.2f} MiB | {med['open_s']:.2f} s "
                    f"(max {max(m['open_s']):.2f}) | {med['first_frame_s']:.2f} s | {med['fps']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
