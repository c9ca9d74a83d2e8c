"""How much of the volume a checkpoint labels with a class of the dynamic filter set (argmax of the 17 logits).

    python -m benchmarks.studies.dynamic_argmax --val W/val RUN_DIR [RUN_DIR ...] [--samples 4]

For each run (``RUN_DIR/checkpoints/last.pt``, EMA weights) and a few validation keyframes spread over the split,
prints the percentage of voxels whose argmax class is in ``occ3d.DYNAMIC_FILTER_CLASSES``: over all voxels, over
voxels with σ ≥ τ, and over camera-visible voxels: whether the dynamic ray filter + disocclusion (ablation row 5)
stop the model from predicting those classes at all.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from occflownet.occ3d import DYNAMIC_FILTER_CLASSES
from occflownet.data.loaders import load_occupancy, load_sample_images
from occflownet.eval.evaluate import select_samples
from occflownet.model.checkpoint import load_checkpoint
from occflownet.render.disocclusion import dynamic_mask


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="training run folders (with checkpoints/last.pt)")
    ap.add_argument("--val", required=True, help="prepared validation root")
    ap.add_argument("--samples", type=int, default=4, help="keyframes, spread evenly over the split")
    args = ap.parse_args()
    samples = select_samples(args.val, split="all")
    picks = np.linspace(0, len(samples) - 1, args.samples).round().astype(int)
    records = [samples.index[int(samples.positions[i])] for i in picks]
    print(f"{len(records)} keyframes of {args.val}; dynamic filter set {list(DYNAMIC_FILTER_CLASSES)}")
    for run in args.runs:
        model, _, _ = load_checkpoint(f"{run}/checkpoints/last.pt")
        model.eval()
        everywhere, occupied, visible = [], [], []
        for record in records:
            images = torch.from_numpy(load_sample_images(samples.dataroot, record))[None]
            intrinsics = torch.from_numpy(np.asarray(record.intrinsics, np.float32))[None]
            cam2ego = torch.from_numpy(np.asarray(record.cam2current_ego(), np.float32))[None]
            with torch.inference_mode():
                out = model(images, intrinsics, cam2ego)
            is_dynamic = dynamic_mask(out["logits"][0]).numpy()  # the mask disocclusion uses
            above = (out["density"][0] >= model.cfg.threshold).numpy()
            mask = load_occupancy(samples.dataroot, record.occupancy_path).mask_camera.astype(bool)
            everywhere.append(is_dynamic.mean())
            occupied.append(is_dynamic[above].mean() if above.any() else np.nan)
            visible.append(is_dynamic[mask].mean())
        print(f"{run}: argmax in the dynamic set: {100 * np.mean(everywhere):.1f} % of all voxels, "
              f"{100 * np.nanmean(occupied):.1f} % of voxels with σ ≥ τ, {100 * np.mean(visible):.1f} % of "
              f"camera-visible voxels")


if __name__ == "__main__":
    main()
