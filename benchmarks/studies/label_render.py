"""Are the labels a minimum of the rendering loss? Render a keyframe's Occ3D labels (σ = s where occupied, 0 where
free; the labels' classes as logits) along its own training rays (t = 0) under several readings of σ, and compare
with the LiDAR: the depth error and the opacity the labels would render if a model predicted them exactly.

    python -m benchmarks.studies.label_render --dataroot W [--rays 4096] [--positions 1,3,5]

Rows: ``density`` (the official reading: σ per metre, scaled by k = 1, 2, 4, 8, 16: ``RenderConfig.density_scale``;
σ = 1 at occupied voxels) and ``opacity`` (σ = the share of the light a voxel stops, at 0.5, 0.9, 0.99). Columns:
median weight sum (and the share of rays below 0.5), median rendered depth − LiDAR depth (Σ w t, and Σ w t ÷ Σ w),
median |error|, and the share of rays that render their LiDAR class. A reading under which the labels render the
LiDAR depth is one whose optimum the labels can be; docs/results.md quotes the figures.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from occflownet.data.index import load_index
from occflownet.data.loaders import load_occupancy
from occflownet.data.rays import RayBuilder, RayConfig
from occflownet.occ3d import FREE, NUM_CLASSES
from occflownet.render.volume_render import RenderConfig, render_rays

READINGS = [("density", k, 1.0) for k in (1, 2, 4, 8, 16)] + [("opacity", 1, s) for s in (0.5, 0.9, 0.99)]


def label_render(root, positions: list[int], rays_per_keyframe: int) -> list[dict]:
    """One row per reading of :data:`READINGS`, pooled over the keyframes ``positions`` of ``root``."""
    index = load_index(root)
    builder = RayBuilder(index, root, RayConfig(horizon=0))
    rows = {r: [] for r in READINGS}
    for position in positions:
        rays = builder.rays(position)
        rays = rays.take(np.random.default_rng(position).choice(len(rays), min(rays_per_keyframe, len(rays)),
                                                                 replace=False))
        semantics = load_occupancy(root, index[position].occupancy_path).semantics
        occupied = torch.from_numpy(semantics != FREE).float()
        logits = 5.0 * torch.nn.functional.one_hot(torch.from_numpy(semantics).long(), FREE + 1)[..., :NUM_CLASSES]
        for reading, scale, sigma in READINGS:
            out = render_rays(occupied * sigma, logits.float(), torch.from_numpy(rays.origins),
                              torch.from_numpy(rays.directions), RenderConfig(density_scale=scale, sigma_is=reading),
                              torch.Generator().manual_seed(position))
            rows[(reading, scale, sigma)].append((out.weight_sum.numpy(), out.depth.numpy(), rays.depths,
                                                  out.semantics.argmax(-1).numpy() == rays.labels))
    table = []
    for (reading, scale, sigma), parts in rows.items():
        weight, depth, lidar, agree = (np.concatenate(p) for p in zip(*parts))
        error = depth - lidar
        table.append({"reading": reading, "k": scale, "sigma": sigma, "weight_sum_median": float(np.median(weight)),
                      "below_half": float(np.mean(weight < 0.5)), "error_median": float(np.median(error)),
                      "normalised_error_median": float(np.median(depth / np.maximum(weight, 1e-6) - lidar)),
                      "abs_error_median": float(np.median(np.abs(error))), "class_agreement": float(np.mean(agree)),
                      "rays": int(len(error))})
    return table


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataroot", required=True)
    p.add_argument("--rays", type=int, default=4096, help="t = 0 rays per keyframe")
    p.add_argument("--positions", default="1,3,5", help="keyframes (positions in the index)")
    args = p.parse_args(argv)
    table = label_render(args.dataroot, [int(v) for v in args.positions.split(",")], args.rays)
    print("| reading | σ at occupied voxels | weight sum (median) | rays < 0.5 | depth − LiDAR (median) | normalised "
          "(median) | abs error (median) | class agreement |\n|---|---|---|---|---|---|---|---|")
    for r in table:
        what = f"σ × {r['k']}" if r["reading"] == "density" else f"{r['sigma']}"
        print(f"| {r['reading']} | {what} | {r['weight_sum_median']:.2f} | {100 * r['below_half']:.0f} % | "
              f"{r['error_median']:+.2f} m | {r['normalised_error_median']:+.2f} m | {r['abs_error_median']:.2f} m | "
              f"{100 * r['class_agreement']:.0f} % |")
    print(f"({table[0]['rays']} rays of t = 0 from keyframes {args.positions} of {args.dataroot})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
