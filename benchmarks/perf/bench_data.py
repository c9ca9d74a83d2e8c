"""Data-reader figures on a prepared nuScenes-format root: index load time, rays per keyframe, ray build time.

    python -m benchmarks.perf.bench_data --dataroot DIR [--version V] [--horizon 3] [--samples 20] [--repeat 3]
        [--recipes quickstart,recommended] [--split train] [--jsonl PATH]

Run ``occflownet prepare --dataroot DIR`` first. For each of up to ``--samples`` keyframes (evenly spread over the
index) the rays of t ∈ [-O, O] are built (a) cold: no per-frame cache, every sweep of the window is loaded and
projected; (b) sequential: keyframes in scene order with the default per-frame cache (what a sequential loader
sees; a shuffled training loader is closer to cold). Prints the index load time, rays and frames per keyframe and
best-of-``--repeat`` medians of the ray build (the machine may be shared), with the load average and the float32
matmul rate (appended to ``--jsonl``); then, per t, the share of ray endpoints whose Occ3D voxel holds the ray's
label. With ``--recipes``: per recipe, the training loader's own sample (``train.dataset.TrainingSamples``, what one
data worker builds for a step: images, rays, labels) over every keyframe of ``--split``, after one pass that fills
its caches, in a shuffled order, ``--repeat`` passes: the mean ms a sample (what a worker of a long run spends).
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from benchmarks.harness import Results, add_jsonl_option
from occflownet.occ3d import STATIC_CLASSES
from occflownet.data import load_index
from occflownet.data.loaders import load_occupancy
from occflownet.data.rays import RayBuilder, RayConfig, endpoint_classes


def options() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataroot", required=True)
    p.add_argument("--version", default=None)
    p.add_argument("--horizon", type=int, default=3)
    p.add_argument("--samples", type=int, default=20)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--recipes", default="", help="comma-separated recipe names: time their training samples instead")
    p.add_argument("--split", default="train", help="split of the training samples (--recipes)")
    add_jsonl_option(p)
    return p.parse_args()


def main() -> None:
    args = options()
    results = Results("bench_data", args.jsonl)
    if args.recipes:
        for name in args.recipes.split(","):
            training_samples(name, args, results)
        return

    t = time.perf_counter()
    index = load_index(args.dataroot, args.version)
    load_s = time.perf_counter() - t
    positions = np.unique(np.linspace(0, len(index) - 1, min(args.samples, len(index))).astype(int))
    config = RayConfig(horizon=args.horizon)
    print(f"root {args.dataroot} ({index.version}): {len(index)} keyframes; load_index {load_s * 1e3:.1f} ms")

    full = 2 * args.horizon + 1
    cold, cold_full, rays, frames = [], [], [], []
    for _ in range(args.repeat):
        times, times_full = [], []
        for pos in positions:
            builder = RayBuilder(index, args.dataroot, config, cache_size=0)
            t = time.perf_counter()
            batch = builder.rays(int(pos))
            times.append(time.perf_counter() - t)
            rays.append(len(batch))
            frames.append(len(np.unique(batch.time_offsets)))
            if frames[-1] == full:
                times_full.append(times[-1])
        cold.append(statistics.median(times))
        if times_full:
            cold_full.append(statistics.median(times_full))
    sequential = []
    for _ in range(args.repeat):
        builder = RayBuilder(index, args.dataroot, config)
        t = time.perf_counter()
        for pos in range(len(index)) if len(index) <= 200 else positions:
            builder.rays(int(pos))
        sequential.append((time.perf_counter() - t) / (len(index) if len(index) <= 200 else len(positions)))
    lines = [f"horizon {args.horizon}: {statistics.median(frames):.0f} frames/keyframe (median), "
             f"{statistics.median(rays):,.0f} rays/keyframe (median)",
             f"rays per keyframe, cold (no cache): {min(cold) * 1e3:.0f} ms (median over {len(positions)} keyframes, "
             f"best of {args.repeat})"]
    if cold_full:
        lines.append(f"rays per keyframe with all {full} frames, cold: {min(cold_full) * 1e3:.0f} ms (median, best of "
                     f"{args.repeat})")
    lines.append(f"rays per keyframe, sequential with cache: {min(sequential) * 1e3:.0f} ms (mean, best of "
                 f"{args.repeat})")
    results.add({"dataroot": args.dataroot, "keyframes": len(index), "load_index_ms": load_s * 1e3,
                 "horizon": args.horizon, "frames_per_keyframe": statistics.median(frames),
                 "rays_per_keyframe": statistics.median(rays), "cold_ms": min(cold) * 1e3,
                 "cold_all_frames_ms": min(cold_full) * 1e3 if cold_full else None,
                 "sequential_ms": min(sequential) * 1e3}, "\n".join(lines))
    agreement(index, args.dataroot, config, positions)


def training_samples(recipe: str, args, results: Results) -> None:
    """Mean ms of a training sample of ``recipe`` on the split's keyframes, caches filled, in shuffled order."""
    from occflownet.train import loop
    from occflownet.train.dataset import TrainingSamples
    from occflownet.train.recipe import TrainConfig

    cfg = TrainConfig.from_recipe(recipe, dataroot=args.dataroot, split=args.split, out="unused", num_workers=0)
    index, positions, flows = loop._training_data(cfg)
    samples = TrainingSamples(cfg.dataroot, index, positions, cfg, flows)
    for i in range(len(samples)):                                  # the first pass fills the caches
        samples[(i, 0)]
    passes = []
    for step in range(1, args.repeat + 1):
        t = time.perf_counter()
        for i in np.random.default_rng(step).permutation(len(samples)):
            samples[(int(i), step)]
        passes.append((time.perf_counter() - t) / len(samples))
    results.add({"dataroot": args.dataroot, "recipe": recipe, "samples": len(samples),
                 "sample_ms": statistics.mean(passes) * 1e3},
                f"{recipe}: a training sample {statistics.mean(passes) * 1e3:.1f} ms (mean over {len(samples)} "
                f"keyframes of split {args.split}, caches filled, {args.repeat} shuffled passes)")


def agreement(index, dataroot, config: RayConfig, positions) -> None:
    """Fraction of ray endpoints whose Occ3D voxel (current keyframe's ground truth) holds the ray's label, per t,
    for all rays and for rays of static classes, over the keyframes in ``positions`` that have occupancy."""
    builder = RayBuilder(index, dataroot, config)
    hits = {}
    for pos in positions:
        if index[int(pos)].occupancy_path is None:
            continue
        rays = builder.rays(int(pos))
        same = endpoint_classes(rays, load_occupancy(dataroot, index[int(pos)].occupancy_path).semantics) \
            == rays.labels
        static = np.isin(rays.labels, STATIC_CLASSES)
        for t in np.unique(rays.time_offsets):
            m = rays.time_offsets == t
            a = hits.setdefault(int(t), [0, 0, 0, 0])
            a[0] += int(same[m].sum())
            a[1] += int(m.sum())
            a[2] += int(same[m & static].sum())
            a[3] += int((m & static).sum())
    if not hits:
        print("no keyframe with Occ3D occupancy: no label agreement figures")
        return
    print("endpoint voxel label == ray label (current keyframe's Occ3D gt): t, all rays, static-class rays")
    for t in sorted(hits):
        a = hits[t]
        print(f"  t={t:+d}: {a[0] / max(a[1], 1):.3f} of {a[1]:,}   static {a[2] / max(a[3], 1):.3f} of {a[3]:,}")


if __name__ == "__main__":
    main()
