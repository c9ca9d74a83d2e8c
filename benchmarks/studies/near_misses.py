"""How far a model's errors on scenes it never saw lie from the labels: per-class IoU inside mask_camera when a
voxel counts as found if the other grid holds its class within r voxels.

    python -m benchmarks.studies.near_misses --checkpoint RUN/checkpoints/last.pt --dataroot W [--split val]
        [--radii 0,1,2] [--every 1]

At radius r a labelled voxel of class c is a hit when a voxel predicted c lies within r voxels of it (the cube of
side 2r + 1, Chebyshev distance), a predicted voxel of class c is a false positive when no labelled voxel of c lies
within r; both counted inside ``mask_camera`` (the neighbours may lie outside it). IoU_r = hits / (hits + misses +
false positives); at r = 0 it is the evaluation's IoU (``occflownet eval``). A class whose IoU rises from r = 0 to
r = 1 (0.4 m) was placed beside its labels, not missed: a matter of depth and surface placement, not of recognition.
Also printed per class: the share of its labelled voxels predicted free and predicted as another class (r = 0).
"""
from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from occflownet.eval.metrics import nanmean
from occflownet.occ3d import CLASS_NAMES, FREE

NUM = FREE          # the occupied classes 0 .. 16


def near_counts(pred: np.ndarray, label: np.ndarray, mask: np.ndarray, radius: int):
    """Occupancy grids ``pred`` and ``label`` (uint8 [X, Y, Z], class ids, FREE = 17) and ``mask`` (bool [X, Y, Z]) →
    (hits, misses, false positives), int64 [NUM] each: labelled voxels of class c inside ``mask`` with / without a
    voxel predicted c within ``radius`` voxels (Chebyshev), and predicted voxels of c inside ``mask`` without a
    labelled voxel of c within ``radius``."""
    hits, misses, false_pos = (np.zeros(NUM, np.int64) for _ in range(3))
    size = 2 * radius + 1
    for c in range(NUM):
        lab, prd = label == c, pred == c
        if not (lab.any() or prd.any()):
            continue
        near_pred = ndimage.maximum_filter(prd, size=size) if radius else prd
        near_label = ndimage.maximum_filter(lab, size=size) if radius else lab
        lab_in = lab & mask
        hits[c] = np.count_nonzero(lab_in & near_pred)
        misses[c] = np.count_nonzero(lab_in & ~near_pred)
        false_pos[c] = np.count_nonzero(prd & mask & ~near_label)
    return hits, misses, false_pos


def iou(hits: np.ndarray, misses: np.ndarray, false_pos: np.ndarray) -> np.ndarray:
    """Per-class IoU float [NUM], NaN for a class neither labelled nor predicted."""
    total = hits + misses + false_pos
    return np.where(total > 0, hits / np.maximum(total, 1), np.nan)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--dataroot", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--radii", default="0,1,2", help="comma-separated radii in voxels (0.4 m each)")
    ap.add_argument("--every", type=int, default=1)
    args = ap.parse_args()

    from dataclasses import replace

    from occflownet.eval.evaluate import predictions, select_samples
    from occflownet.model import model_from_source
    from occflownet.runtime import TorchPredictor

    radii = [int(r) for r in args.radii.split(",")]
    if any(r < 0 for r in radii):
        raise SystemExit(f"--radii must be >= 0, got {args.radii}")
    samples = select_samples(args.dataroot, split=args.split)
    samples = replace(samples, positions=samples.positions[::args.every])
    counts = {r: np.zeros((3, NUM), np.int64) for r in radii}
    as_free, as_other, labelled = np.zeros(NUM), np.zeros(NUM), np.zeros(NUM)
    for _, _, occupancy, _, labels in predictions(samples, TorchPredictor(model_from_source(args.checkpoint))):
        mask = labels.mask_camera.astype(bool)
        for r in radii:
            counts[r] += np.stack(near_counts(occupancy, labels.semantics, mask, r))
        lab = labels.semantics[mask]
        prd = occupancy[mask]
        occupied = lab != FREE
        labelled += np.bincount(lab[occupied], minlength=NUM + 1)[:NUM]
        as_free += np.bincount(lab[occupied & (prd == FREE)], minlength=NUM + 1)[:NUM]
        as_other += np.bincount(lab[occupied & (prd != FREE) & (prd != lab)], minlength=NUM + 1)[:NUM]
    ious = {r: iou(*counts[r]) for r in radii}
    print(f"{args.checkpoint}: {len(samples)} keyframes of split {args.split!r} of {args.dataroot}")
    print("| class | " + " | ".join(f"IoU r={r}" for r in radii) + " | labelled voxels | predicted free | "
          "predicted another class |")
    print("|---|" + "---|" * (len(radii) + 3))
    print("| **mIoU** | " + " | ".join(f"**{100 * nanmean(ious[r]):.1f}**" for r in radii) + " | | | |")
    for c, name in enumerate(CLASS_NAMES[:NUM]):
        if np.isnan(ious[radii[0]][c]):
            continue
        n = max(labelled[c], 1)
        print(f"| {name} | " + " | ".join(f"{100 * ious[r][c]:.1f}" for r in radii)
              + f" | {int(labelled[c])} | {100 * as_free[c] / n:.0f} % | {100 * as_other[c] / n:.0f} % |")


if __name__ == "__main__":
    main()
