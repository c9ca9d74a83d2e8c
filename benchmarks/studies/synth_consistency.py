"""Consistency figures of the synthetic world: do LiDAR labels, the geometric truth and image depth agree?

    python -m benchmarks.studies.synth_consistency [--scenes 2 --frames 6 --seed 0 --width 480 --height 270]

Prints, over all keyframes:
- LiDAR → truth: share of keyframe LiDAR points inside the grid whose voxel in the geometric truth has the point's own
  class (``occflownet.synth.consistency.lidar_label_agreement``: read back from the files on disk); per class too.
- LiDAR → image depth: for every LiDAR point projected into a camera (``lidar_camera_depths``), |z-depth of the
  point − depth of the camera ray through its exact projection| and |… − rendered depth at its pixel|; share
  within 1 cm and 0.5 m, for all points and for points of static objects (dynamic agents move between LiDAR and
  camera times).
- the labels (gts/, made by the label pipeline): mean of mask_lidar / mask_camera, classes present.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from occflownet.occ3d import CLASS_NAMES
from occflownet.synth.consistency import lidar_camera_depths, lidar_label_agreement
from occflownet.synth.frame import SensorRig
from occflownet.synth.generate import FIRST_TIMESTAMP_US, generate
from occflownet.synth.layout import WorldConfig, build_world


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--height", type=int, default=270)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        res = generate(root, scenes=args.scenes, frames=args.frames, seed=args.seed, width=args.width,
                       height=args.height, progress=False)
        own, vox = lidar_label_agreement(root, res.version)
        masks = []
        for p in sorted((root / "gts").glob("*/*/labels.npz")):
            with np.load(p) as z:
                masks.append((z["mask_lidar"].mean(), z["mask_camera"].mean(), np.unique(z["semantics"])))
    print(f"LiDAR points inside the grid: {len(own)}; in a truth voxel of their own class: {np.mean(own == vox):.4f}")
    for c in range(17):
        sel = own == c
        if sel.any():
            print(f"  {CLASS_NAMES[c]:22s} {sel.sum():8d} points  agreement {np.mean(vox[sel] == c):.4f}")
    rig = SensorRig.default(args.width, args.height)
    parts = []
    for s in range(args.scenes):
        world = build_world(WorldConfig(), args.seed, s, args.frames)
        parts.append(lidar_camera_depths(world, rig, FIRST_TIMESTAMP_US + s * 1_000_000_000, args.seed, s,
                                         range(0, args.frames, 2)))
    r = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    r["exact"], r["pixel"] = np.abs(r["lidar"] - r["ray"]), np.abs(r["lidar"] - r["pixel"])
    st = r["static"]
    print(f"LiDAR points projected into cameras: {len(st)} (every 2nd keyframe; {st.mean():.3f} on static things)")
    for key, name in (("exact", "camera ray through the exact projection"), ("pixel", "rendered pixel")):
        e = r[key]
        print(f"  vs {name}: |depth error| < 0.01 m: all {np.mean(e < 0.01):.4f}, static {np.mean(e[st] < 0.01):.4f};"
              f" < 0.5 m: all {np.mean(e < 0.5):.4f}, static {np.mean(e[st] < 0.5):.4f}; median {np.median(e):.4f} m")
    print(f"  the pixel shows the point's class: all {r['class_ok'].mean():.4f}, static {r['class_ok'][st].mean():.4f}")
    ml, mc, present = zip(*masks)
    classes = set(np.concatenate(present).tolist()) - {17}
    print(f"mask_lidar mean {np.mean(ml):.4f}, mask_camera mean {np.mean(mc):.4f}; "
          f"classes present in gt: {len(classes)}/17 {sorted(classes)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
