"""Do the training rays agree with the labels they are meant to fit? Per keyframe and time offset: how many rays
end on a class, and how many pass through a labelled voxel of that class well before their point (they tell the
renderer "free" where the labels say "occupied"), with and without ``--box-line-of-sight`` (docs/data.md).

    python -m benchmarks.studies.ray_sight --dataroot ROOT [--positions 2,5] [--classes car,bus,truck] [--rays 4000]

A ray "passes through" class c when a point sampled every 5 cm on it, more than ``--before`` metres before its end,
lies in a voxel labelled c (the keyframe's Occ3D labels, current ego frame). Counts of passing rays are estimated
from ``--rays`` rays drawn per (keyframe, t) and scaled to all of them. Free rays (``--free-beyond-grid``) are
counted up to their grid exit.
"""
from __future__ import annotations

import argparse

import numpy as np

from occflownet.data.index import load_index
from occflownet.data.loaders import load_occupancy
from occflownet.data.rays import RayBuilder, RayConfig
from occflownet.occ3d import CLASS_NAMES, GRID

STEP = 0.05  # metres between samples along a ray


def passing(origins, directions, lengths, semantics, classes, before, n, rng) -> np.ndarray:
    """Estimated number of rays [len(classes)] that pass through a voxel of each class ``before`` m before their
    end (all rays when ``n`` ≥ their number, else ``n`` drawn ones, scaled)."""
    if len(origins) == 0:
        return np.zeros(len(classes))
    pick = rng.choice(len(origins), min(n, len(origins)), replace=False)
    counts = np.zeros(len(classes))
    for i in pick:
        s = np.arange(STEP, max(min(lengths[i], 120.0) - before, 0.0), STEP)
        p = origins[i] + s[:, None] * directions[i]
        p = p[GRID.contains(p)]
        if len(p):
            ijk = GRID.index_of(p)
            counts += np.isin(classes, semantics[ijk[:, 0], ijk[:, 1], ijk[:, 2]])
    return counts * len(origins) / len(pick)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataroot", required=True)
    ap.add_argument("--positions", default="2,5", help="keyframe positions in the index")
    ap.add_argument("--classes", default="car,bus,truck,manmade")
    ap.add_argument("--horizon", type=int, default=3)
    ap.add_argument("--before", type=float, default=0.6, help="metres before the ray's end that count")
    ap.add_argument("--rays", type=int, default=4000, help="rays drawn per (keyframe, t) for the passing counts")
    args = ap.parse_args()
    index = load_index(args.dataroot)
    names = args.classes.split(",")
    classes = np.array([CLASS_NAMES.index(c) for c in names])
    print(f"| keyframe | line of sight | t | rays | " + " | ".join(f"end on {c} | through {c}" for c in names)
          + " | free rays | free through " + "/".join(names) + " |")
    print("|---" * (5 + 2 * len(names) + 2) + "|")
    for position in (int(p) for p in args.positions.split(",")):
        semantics = load_occupancy(args.dataroot, index[position].occupancy_path).semantics
        for sight in (False, True):
            rng = np.random.default_rng(0)
            builder = RayBuilder(index, args.dataroot, RayConfig(horizon=args.horizon, beyond_grid=True,
                                                                 box_line_of_sight=sight))
            rays, free = builder.rays(position), builder.free_rays(position)
            for t, _ in index.neighbours(position, args.horizon):
                r, f = rays.take(rays.time_offsets == t), free.take(free.time_offsets == t)
                through = passing(r.origins, r.directions, r.depths, semantics, classes, args.before, args.rays, rng)
                free_through = passing(f.origins, f.directions, np.full(len(f), np.inf), semantics, classes, 0.0,
                                       args.rays, rng)
                cells = " | ".join(f"{int((r.labels == c).sum())} | {through[k]:.0f}" for k, c in enumerate(classes))
                print(f"| {position} | {'on' if sight else 'off'} | {t:+d} | {len(r)} | {cells} | {len(f)} | "
                      + "/".join(f"{v:.0f}" for v in free_through) + " |", flush=True)


if __name__ == "__main__":
    main()
