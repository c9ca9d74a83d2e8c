"""Rendering throughput on CPU: occflownet's renderer vs a naive grid_sample renderer, forward + backward.

    python -m benchmarks.perf.bench_render [--rays 32768] [--repeats 2] [--threads N] [--jsonl PATH]

Scene: the Occ3D sample labels (../shared/data/occ3d-sample/labels.npz) turned into a "trained-looking" volume
(σ = 0.95 in occupied voxels, 0.02 in free ones, plus noise; logits = 4·one-hot + noise), and camera rays of the
shared nuScenes frame (../shared/data/nuscenes-frame: six camera centres → LiDAR points that project into that
camera). Without the shared data it falls back to a synthetic volume (ground + boxes) and random rays and says so.

Printed: rendered samples per second (n_coarse + n_fine per ray), each with the load average and the float32 matmul
rate (appended to ``--jsonl``), for
- ``naive``: F.grid_sample on the [1, 18, Z, Y, X] volume (σ + 17 logits) at all 150 samples, with autograd
  through both lookups, then the same weights/depth/semantics formulas;
- ``grid_sample``: occflownet's renderer with ``lookup="grid_sample"`` (coarse pass σ-only without grad);
- ``numba``: occflownet's renderer on CPU (``lookup="auto"``: the numba kernels), with as many threads as torch
  uses for the naive one (``--threads``, default: torch's default), and ``numba-1t`` with one thread;
then the speed-up, and the accuracy of depth and semantics for naive and numba (both float32) against the naive
renderer run in float64 on the same rays (the exact answer up to float64 rounding), plus their difference to
each other. The coarse-to-fine draws invert a CDF that is flat in places, so float32 rounding moves a few fine
samples by up to ~1 mm in either renderer; the float64 comparison shows which one is closer to the exact render.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
import torch.nn.functional as F

from benchmarks.harness import SHARED_DATA, Results, add_jsonl_option
from occflownet.occ3d import GRID, NUM_CLASSES
from occflownet.render.sampling import (cdf_from_sigma, importance_sample, intervals_from_samples,
                                        uniform_jittered_edges)
from occflownet.render.volume_render import RenderConfig, render_rays, weights_from_density

SHARED = SHARED_DATA


def load_scene(n_rays: int, rng: np.random.Generator):
    """→ (density [1,X,Y,Z], logits [1,X,Y,Z,17], origins [R,3], directions [R,3], description)."""
    labels_path = SHARED / "occ3d-sample" / "labels.npz"
    frame = SHARED / "nuscenes-frame"
    if labels_path.exists() and (frame / "calib.json").exists():
        sem = np.load(labels_path)["semantics"].astype(np.int64)
        calib = json.loads((frame / "calib.json").read_text())
        pts = np.fromfile(frame / "lidar.bin", dtype=np.float32).reshape(-1, 5)[:, :3].astype(np.float64)
        lidar2ego = np.asarray(calib["lidar2ego"], dtype=np.float64)
        pts = pts @ lidar2ego[:3, :3].T + lidar2ego[:3, 3]
        w, h = calib["image_size"]
        origins, targets = [], []
        for cam in calib["cameras"].values():
            cam2ego, k = np.asarray(cam["cam2ego"]), np.asarray(cam["intrinsic"])
            pc = (pts - cam2ego[:3, 3]) @ cam2ego[:3, :3]
            z = pc[:, 2]
            uv = pc @ k.T
            ok = z > 0.05
            u, v = uv[ok, 0] / z[ok], uv[ok, 1] / z[ok]
            sel = np.nonzero(ok)[0][(u >= 0) & (u < w) & (v >= 0) & (v < h)]
            sel = sel[GRID.contains(pts[sel])]
            origins.append(np.repeat(cam2ego[None, :3, 3], len(sel), 0))
            targets.append(pts[sel])
        origins, targets = np.concatenate(origins), np.concatenate(targets)
        pick = rng.choice(len(origins), n_rays, replace=len(origins) < n_rays)
        origins, targets = origins[pick], targets[pick]
        what = f"Occ3D sample volume, {n_rays} camera rays to LiDAR points of the shared nuScenes frame"
    else:
        sem = np.full(GRID.shape, 17, dtype=np.int64)
        sem[:, :, 0] = 11
        for _ in range(60):
            x, y = rng.integers(0, 190, 2)
            sem[x:x + 10, y:y + 5, 1:5] = rng.integers(0, 17)
        origins = np.tile([[1.0, 0.0, 1.6]], (n_rays, 1))
        targets = np.stack([rng.uniform(-39, 39, n_rays), rng.uniform(-39, 39, n_rays),
                            rng.uniform(-1, 2, n_rays)], -1)
        what = f"SYNTHETIC volume and {n_rays} random rays (shared data not found)"
    occupied = torch.from_numpy(sem != 17)
    gen = torch.Generator().manual_seed(0)
    density = torch.where(occupied, 0.95, 0.02) + 0.02 * torch.rand(GRID.shape, generator=gen)
    onehot = F.one_hot(torch.from_numpy(np.minimum(sem, 16)), NUM_CLASSES).float()
    logits = 4.0 * onehot + torch.randn(*GRID.shape, NUM_CLASSES, generator=gen)
    directions = targets - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return (density.clamp(0, 1)[None].float(), logits[None].contiguous(),
            torch.from_numpy(origins).float(), torch.from_numpy(directions).float(), what)


def naive_render(density, logits, origins, directions, cfg: RenderConfig, generator):
    """The straightforward renderer: one 18-channel grid_sample lookup for every sample, autograd throughout."""
    volume = torch.cat([density.unsqueeze(-1), logits], -1)[0].permute(3, 2, 1, 0).unsqueeze(0)  # [1,18,Z,Y,X]
    extent = torch.tensor(GRID.shape, dtype=origins.dtype) * GRID.voxel_size
    lower = torch.tensor(GRID.lower, dtype=origins.dtype)

    def lookup(t):  # t [R, N] → values [R, N, 18]
        p = origins[:, None] + t[..., None] * directions[:, None]
        g = ((p - lower) / extent * 2 - 1).reshape(1, 1, 1, -1, 3)
        out = F.grid_sample(volume, g, mode="bilinear", padding_mode="zeros", align_corners=False)
        return out.reshape(18, *t.shape).permute(1, 2, 0)

    n = origins.shape[0]
    edges = uniform_jittered_edges(n, cfg.n_coarse, cfg.near, cfg.far, generator=generator).to(origins.dtype)
    coarse = lookup(0.5 * (edges[:, 1:] + edges[:, :-1]))[..., 0]
    cdf = cdf_from_sigma(edges, coarse.detach(), cfg)       # the official distribution, as the renderer draws it
    t = importance_sample(edges, cdf, cfg.n_fine)
    starts, ends = intervals_from_samples(t, cfg.near, cfg.far)
    values = lookup(t)
    w, _, _ = weights_from_density(values[..., 0], starts, ends)
    return (w * 0.5 * (starts + ends)).sum(-1), (w[..., None] * values[..., 1:]).sum(1)


def timed(fn, repeats: int):
    best, result = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t0)
    return best, result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=32768)
    ap.add_argument("--repeats", type=int, default=2, help="timed runs per method (best is reported)")
    ap.add_argument("--threads", type=int, default=0,
                    help="threads for the naive renderer (torch) and for numba (0: torch's default)")
    add_jsonl_option(ap)
    args = ap.parse_args()
    results_out = Results("bench_render", args.jsonl)
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = RenderConfig()
    density, logits, origins, directions, what = load_scene(args.rays, np.random.default_rng(0))
    density.requires_grad_(True)
    logits.requires_grad_(True)
    per_ray = cfg.n_coarse + cfg.n_fine
    print(f"scene: {what}; torch {torch.__version__}, {torch.get_num_threads()} threads")
    print(f"rays {args.rays} x {per_ray} samples (n_coarse {cfg.n_coarse} + n_fine {cfg.n_fine}), forward+backward "
          f"of depth.mean() + semantics.square().mean(), best of {args.repeats}")

    def step(render):
        density.grad = logits.grad = None
        depth, sem = render()
        (depth.mean() + sem.square().mean()).backward()
        return depth.detach(), sem.detach()

    threads = torch.get_num_threads()
    methods = {
        "naive": lambda: naive_render(density, logits, origins, directions, cfg, torch.Generator().manual_seed(7)),
        "grid_sample": lambda: _ours(density, logits, origins, directions, RenderConfig(lookup="grid_sample")),
        "numba": lambda: _ours(density, logits, origins, directions, RenderConfig(threads=threads)),
        "numba-1t": lambda: _ours(density, logits, origins, directions, RenderConfig(threads=1)),
    }
    _ours(density, logits, origins, directions, RenderConfig(threads=1))  # compile / load the kernels untimed
    results = {}
    for name, render in methods.items():
        seconds, results[name] = timed(lambda: step(render), args.repeats)
        results_out.add({"method": name, "rays": args.rays, "seconds": seconds,
                         "msamples_per_s": args.rays * per_ray / seconds / 1e6},
                        f"{name:12s} {seconds:7.2f} s  {args.rays * per_ray / seconds / 1e6:6.2f} M samples/s")
        results[name] = (seconds, *results[name])
    base = results["naive"]
    print(f"speed-up numba vs naive ({threads} threads each): {base[0] / results['numba'][0]:.1f}x; numba 1 thread "
          f"vs naive {threads} threads: {base[0] / results['numba-1t'][0]:.1f}x; numba vs grid_sample path: "
          f"{results['grid_sample'][0] / results['numba'][0]:.1f}x")
    exact = naive_render(density.detach().double(), logits.detach().double(), origins.double(),
                         directions.double(), cfg, torch.Generator().manual_seed(7))
    for name in ("naive", "numba"):
        print(f"{name:6s} float32 vs exact (float64 naive): max |depth diff| "
              f"{float((results[name][1] - exact[0]).abs().max()):.2e} m, max |semantics diff| "
              f"{float((results[name][2] - exact[1].detach()).abs().max()):.2e}")
    fast = results["numba"]
    print(f"numba vs naive (both float32): max |depth diff| {float((base[1] - fast[1]).abs().max()):.2e} m, max "
          f"|semantics diff| {float((base[2] - fast[2]).abs().max()):.2e}; mean weight sum "
          f"{float(_ours_ws(density, logits, origins, directions, cfg)):.3f}")


def _ours(density, logits, origins, directions, cfg):
    out = render_rays(density, logits, origins, directions, cfg, torch.Generator().manual_seed(7))
    return out.depth, out.semantics


def _ours_ws(density, logits, origins, directions, cfg):
    with torch.no_grad():
        return render_rays(density, logits, origins, directions, cfg,
                           torch.Generator().manual_seed(7)).weight_sum.mean()


if __name__ == "__main__":
    main()
