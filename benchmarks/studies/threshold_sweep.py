"""Geometry IoU, Occ3D mIoU and per-class IoU inside mask_camera as functions of the fusion threshold τ, for one
checkpoint on one split.

    python -m benchmarks.studies.threshold_sweep --checkpoint RUN/checkpoints/last.pt --dataroot W [--split all]
        [--every 1] [--classes car,bus,truck,manmade]

Shows whether a model that scores low at its stored τ has learned geometry whose σ lies on another scale (the
2D rows), where its geometry IoU peaks, and which τ serves the objects of unseen scenes (the quickstart's τ,
docs/training.md). The model runs once per keyframe with the smallest τ, so its occupancy holds the class of every
voxel a τ can keep; each τ then keeps the voxels with σ ≥ τ, scored by the evaluation's own accumulator
(``OccupancyMetric``). Every ``--every``-th keyframe of the split is evaluated.
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
    ap.add_argument("--classes", default="car,bus,truck,manmade", help="classes whose IoU is printed per τ")
    args = ap.parse_args()

    from dataclasses import replace

    from occflownet.eval import OccupancyMetric
    from occflownet.eval.evaluate import predictions, select_samples
    from occflownet.model import model_from_source
    from occflownet.occ3d import CLASS_NAMES, FREE
    from occflownet.runtime import TorchPredictor

    classes = [c for c in args.classes.split(",") if c]
    unknown = sorted(set(classes) - set(CLASS_NAMES))
    if unknown:
        raise SystemExit(f"unknown classes {unknown}; choose from {list(CLASS_NAMES)}")
    samples = select_samples(args.dataroot, split=args.split)
    samples = replace(samples, positions=samples.positions[::args.every])
    model = model_from_source(args.checkpoint)
    stored = model.cfg.threshold
    model.cfg = replace(model.cfg, threshold=min(TAUS))    # every voxel a τ can keep gets its class; τ applied below
    metrics = [OccupancyMetric() for _ in TAUS]
    for _, _, occupancy, density, labels in predictions(samples, TorchPredictor(model)):
        for metric, tau in zip(metrics, TAUS):
            metric.update(np.where(density >= tau, occupancy, FREE).astype(np.uint8), labels.semantics,
                          labels.mask_camera)
    rows = {"geometry IoU %": [], "mIoU %": [], **{f"{c} IoU %": [] for c in classes}}
    for metric in metrics:
        summary = metric.compute()["camera_mask"]
        rows["geometry IoU %"].append(summary["geometry_iou"])
        rows["mIoU %"].append(summary["miou"])
        for c in classes:
            rows[f"{c} IoU %"].append(summary["iou_per_class"][c])
    print(f"{args.checkpoint}: {len(samples)} keyframes of split {args.split!r}, stored τ {stored:g}")
    print("| τ | " + " | ".join(f"{t:g}" for t in TAUS) + " |")
    print("|---|" + "---|" * len(TAUS))
    for name, values in rows.items():
        print(f"| {name} | " + " | ".join(f"{100 * v:.1f}" for v in values) + " |")
    for name in ("geometry IoU %", "mIoU %"):
        values = np.asarray(rows[name], dtype=float)
        print(f"best τ for {name[:-2]}: {TAUS[int(np.nanargmax(values))]:g} ({100 * np.nanmax(values):.1f} %)")


if __name__ == "__main__":
    main()
