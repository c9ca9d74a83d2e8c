"""Geometry IoU inside mask_camera as a function of the fusion threshold τ, for one checkpoint on one split.

    python benchmarks/threshold_sweep.py --checkpoint RUN/checkpoints/last.pt --dataroot W [--split all]

Shows whether a model that scores low at its stored τ has learned geometry whose σ lies on another scale (the
2D rows), and where its geometry IoU peaks. Every ``--every``-th keyframe of the split is evaluated.
"""
from __future__ import annotations

import argparse

import numpy as np

TAUS = (0.02, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--dataroot", required=True)
    ap.add_argument("--split", default="all")
    ap.add_argument("--every", type=int, default=2)
    args = ap.parse_args()

    from dataclasses import replace

    from occflownet.eval.evaluate import predictions, select_samples
    from occflownet.model import model_from_source
    from occflownet.occ3d import FREE
    from occflownet.runtime import TorchPredictor

    samples = select_samples(args.dataroot, split=args.split)
    samples = replace(samples, positions=samples.positions[::args.every])
    tp, fp, fn = (np.zeros(len(TAUS)) for _ in range(3))
    for _, _, _, density, labels in predictions(samples, TorchPredictor(model_from_source(args.checkpoint))):
        mask = labels.mask_camera.astype(bool)
        occupied, sigma = (labels.semantics != FREE)[mask], density[mask]
        for i, tau in enumerate(TAUS):
            pred = sigma >= tau
            tp[i] += np.sum(pred & occupied)
            fp[i] += np.sum(pred & ~occupied)
            fn[i] += np.sum(~pred & occupied)
    iou = tp / np.maximum(tp + fp + fn, 1)
    print("| τ | " + " | ".join(f"{t:g}" for t in TAUS) + " |")
    print("|---|" + "---|" * len(TAUS))
    print("| geometry IoU % | " + " | ".join(f"{100 * v:.1f}" for v in iou) + " |")
    print(f"best τ {TAUS[int(np.argmax(iou))]:g}: {100 * iou.max():.1f} %")


if __name__ == "__main__":
    main()
