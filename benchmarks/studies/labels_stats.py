"""The label pipeline's figures (docs/data.md): label statistics of the real Occ3D sample, of the real nuScenes
frame labelled geometry-only, and of synthetic worlds labelled by the pipeline; the synthetic labels against the
world's geometric truth; and the labeller's speed on a 40-keyframe scene.

    python -m benchmarks.studies.labels_stats [--world DIR ...] [--speed-frames 40] [--no-speed]

Without --world, a fresh 1 scene × 8 keyframe world (seed 0, 480 × 270) is generated in a temporary folder.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import SHARED_DATA
from occflownet.data.builder import build_index
from occflownet.data.frame_root import write_frame_root
from occflownet.data.loaders import load_occupancy
from occflownet.labels import LabelConfig, label_root
from occflownet.labels.stats import label_stats, mean_stats, truth_agreement
from occflownet.synth.generate import generate, load_truth

SHARED = SHARED_DATA
ROWS = (("voxels in mask_camera", "mask_camera", "{:,.0f}"), ("share of the grid", "mask_camera_share", "{:.1%}"),
        ("mask_camera outside mask_lidar", "mask_camera_outside_lidar", "{:,.0f}"),
        ("occupied in mask_camera", "occupied_in_camera", "{:,.0f}"),
        ("free in mask_camera", "free_in_camera", "{:,.0f}"),
        ("free per occupied in mask_camera", "free_per_occupied", "{:.1f}"),
        ("occupied voxels in mask_camera", "occupied_share_in_camera", "{:.0%}"),
        ("columns holding ground", "ground_columns", "{:,.0f}"))


def world_stats(root: Path) -> tuple[dict, dict | None]:
    """(mean label_stats, mean truth_agreement or None) over every keyframe of a root with gts/."""
    index = build_index(root)
    stats, agree = [], []
    for p in range(len(index)):
        s = index[p]
        lab = load_occupancy(root, s.occupancy_path)
        stats.append(label_stats(lab.semantics, lab.mask_lidar, lab.mask_camera))
        if (root / "truth").is_dir():
            agree.append(truth_agreement(lab.semantics, lab.mask_camera, load_truth(root, s.scene_name, s.token)))
    return mean_stats(stats), (mean_stats(agree) if agree else None)


def frame_stats(tmp: Path) -> dict:
    root = write_frame_root(SHARED / "nuscenes-frame", tmp / "frame")
    label_root(root, config=LabelConfig(geometry_only=True), progress=False)
    return world_stats(root)[0]


def print_table(columns: dict[str, dict]) -> None:
    for stats in columns.values():
        stats["free_per_occupied"] = stats["free_in_camera"] / max(stats["occupied_in_camera"], 1)
    print("| per keyframe | " + " | ".join(columns) + " |")
    print("|---|" + "---|" * len(columns))
    for name, key, fmt in ROWS:
        print(f"| {name} | " + " | ".join(fmt.format(c[key]) for c in columns.values()) + " |")
    print("\nfree voxels in mask_camera by layer (z from -1.0 m, 0.4 m per layer):")
    for label, c in columns.items():
        print(f"  {label}: " + " ".join(f"{v:.0f}" for v in c["free_in_camera_by_layer"]))


def speed(tmp: Path, frames: int) -> None:
    root = tmp / f"speed_1x{frames}"
    generate(root, scenes=1, frames=frames, seed=3, progress=False)
    start = time.perf_counter()
    report = label_root(root, overwrite=True, progress=False)
    wall = time.perf_counter() - start
    per = np.array([k["seconds"] for k in report.keyframes])
    print(f"\nspeed: 1 scene x {frames} keyframes (whole-scene window, {len(list((root / 'sweeps').rglob('*.bin')))}"
          f" sweeps between keyframes): {wall:.1f} s, {wall / frames:.2f} s per keyframe "
          f"(loading and classifying the scene's {report.keyframes[0]['points']:,} points once: "
          f"{wall - per.sum():.1f} s; per keyframe median {np.median(per):.2f} s)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", action="append", default=[], help="synthetic roots to measure (default: a fresh one)")
    ap.add_argument("--speed-frames", type=int, default=40)
    ap.add_argument("--no-speed", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        worlds = [Path(w) for w in args.world]
        if not worlds:
            generate(tmp / "world", scenes=1, frames=8, seed=0, progress=False)
            worlds = [tmp / "world"]
        columns = {"real Occ3D sample": label_stats(**dict(np.load(SHARED / "occ3d-sample" / "labels.npz"))),
                   "real nuScenes frame, geometry only": frame_stats(tmp)}
        agreements = {}
        for w in worlds:
            columns[f"synthetic {w.name}"], agreements[w.name] = world_stats(w)
        print_table(columns)
        for name, a in agreements.items():
            if a:
                print(f"\n{name} against its geometric truth, inside its own mask_camera: precision of the occupied "
                      f"voxels {a['precision']:.2%}, class agreement on them {a['class_agreement']:.2%}, share of "
                      f"the truth's occupied voxels found {a['recall']:.2%}")
        if not args.no_speed:
            speed(tmp, args.speed_frames)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
