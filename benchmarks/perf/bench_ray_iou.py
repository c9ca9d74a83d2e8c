"""Seconds per sample of the CPU RayIoU (and of the Occ3D mIoU update), on a few kinds of 200×200×16 scenes.

    python -m benchmarks.perf.bench_ray_iou [--origins 8] [--repeats 3] [--jsonl PATH]

Each sample casts the reference's 14,040 LiDAR-pattern rays from every origin through the ground truth, then
through the prediction for the rays with a ground-truth hit (as the reference keeps only those). Scenes:
- street: road, sidewalks, building rows, trees, parked cars (a structured, nuScenes-like layout); the
  prediction is the ground truth shifted by one voxel with 5 % of its occupied voxels relabelled;
- sparse: 0.5 % random occupancy, no ground: most rays run to the grid border (the slow case);
- real: the shared Occ3D sample (../shared/data/occ3d-sample/labels.npz), if present, prediction shifted.
Prints per scene the median seconds per sample of each, with the load average and the float32 matmul rate
(appended to ``--jsonl``).
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from benchmarks.harness import SHARED_DATA, Results, add_jsonl_option
from occflownet.eval import OccupancyMetric, RayIoUMetric

LABELS = SHARED_DATA / "occ3d-sample" / "labels.npz"


def street_scene(rng: np.random.Generator) -> np.ndarray:
    vol = np.full((200, 200, 16), 17, dtype=np.uint8)
    vol[:, :, 0:2] = 14  # terrain
    vol[:, 85:115, 0:2] = 11  # road along x
    vol[:, 78:85, 0:3] = 13  # sidewalks
    vol[:, 115:122, 0:3] = 13
    for x0 in range(0, 200, 25):  # building rows with gaps
        vol[x0:x0 + 18, 60:75, 2:16] = 15
        vol[x0 + 5:x0 + 22, 125:140, 2:13] = 15
    for x0 in rng.integers(0, 190, 12):  # trees
        y0 = int(rng.choice([76, 122]))
        vol[x0:x0 + 3, y0:y0 + 3, 3:12] = 16
    for x0 in rng.integers(0, 188, 10):  # parked cars
        y0 = int(rng.choice([86, 109]))
        vol[x0:x0 + 11, y0:y0 + 5, 2:6] = 4
    return vol


def noisy_prediction(gt: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    pred = np.roll(gt, 1, axis=0)
    occupied = np.flatnonzero(pred != 17)
    flip = rng.choice(occupied, size=len(occupied) // 20, replace=False)
    pred.flat[flip] = rng.integers(0, 17, size=len(flip))
    return pred


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--origins", type=int, default=8, help="ray origins per sample (reference: up to 8)")
    parser.add_argument("--repeats", type=int, default=3, help="timed samples per scene (median reported)")
    add_jsonl_option(parser)
    args = parser.parse_args()
    results = Results("bench_ray_iou", args.jsonl)

    rng = np.random.default_rng(0)
    # LiDAR origins of neighbouring keyframes, in the current ego frame: along the road, ~4.5 m apart
    origins = np.array([[0.98 + 4.5 * (k - args.origins // 2), 0.0, 1.84] for k in range(args.origins)])
    scenes = {"street": street_scene(rng)}
    sparse = np.where(rng.random((200, 200, 16)) < 0.005, rng.integers(0, 17, (200, 200, 16)), 17)
    scenes["sparse"] = sparse.astype(np.uint8)
    if LABELS.exists():
        scenes["real"] = np.load(LABELS)["semantics"]

    print(f"{args.origins} origins × 14040 rays = {args.origins * 14040} rays per sample, "
          f"median of {args.repeats} samples")
    for name, gt in scenes.items():
        pred = noisy_prediction(gt, rng) if name != "sparse" else np.roll(gt, 1, axis=0)
        ray_times, occ_times = [], []
        for _ in range(args.repeats):
            metric = RayIoUMetric()
            start = time.perf_counter()
            metric.update(pred, gt, origins)
            ray_times.append(time.perf_counter() - start)
            occ = OccupancyMetric()
            start = time.perf_counter()
            occ.update(pred, gt, gt != 17)
            occ_times.append(time.perf_counter() - start)
        res = metric.compute()
        results.add({"scene": name, "origins": args.origins, "rayiou_s_per_sample": statistics.median(ray_times),
                     "miou_update_ms_per_sample": 1000 * statistics.median(occ_times),
                     "rays_with_gt_hit": res["rays_with_gt_hit"]},
                    f"{name:7s} RayIoU {statistics.median(ray_times):.3f} s/sample "
                    f"({res['rays_with_gt_hit']} rays with a gt hit; RayIoU {100 * res['rayiou']:.1f}) | "
                    f"Occ3D mIoU update {1000 * statistics.median(occ_times):.1f} ms/sample")


if __name__ == "__main__":
    main()
