"""Time and peak memory of one `tiny` training step (data excluded), per recipe, each in its own process.

    python -m benchmarks.perf.bench_train_step --dataroot W [--steps 5] [--rays 4096] [--recipes recommended,paper]
        [--jsonl PATH]

W is a prepared root (`occflownet prepare`; the recipes with 3D labels need its Occ3D labels). A recipe is a name of
``occflownet/train/recipes.py`` (``TrainConfig.from_recipe``). Prints per recipe the seconds per step (forward,
losses incl. rendering/warp, backward; median of --steps after one warm-up step; the batches are loaded before
each step, untimed) and the peak resident memory of the process, with the load average and the float32 matmul rate;
appends each to ``--jsonl``. The data loading's share of a step: ``benchmarks/perf/profile_step.py``.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

from benchmarks.harness import Results, add_jsonl_option, module_argv, tree_env


def one(dataroot: str, name: str, steps: int, rays: int) -> dict:
    import numpy as np
    import torch

    from occflownet.data.flow import flow_path, load_flow_records
    from occflownet.data.index import load_index
    from occflownet.model import create_model, get_preset
    from occflownet.train.recipe import TrainConfig
    from occflownet.train.dataset import TrainingSamples, collate
    from occflownet.train.step import LossComputer

    cfg = TrainConfig.from_recipe(name, dataroot=dataroot, split="all", rays_per_step=rays)
    index = load_index(dataroot)
    flows = load_flow_records(flow_path(dataroot, index.version)) if cfg.flow else None
    data = TrainingSamples(dataroot, index, index.split_positions("all"), cfg, flows)
    model_cfg = get_preset("tiny")
    model = create_model(model_cfg, seed=0).train()
    weights = torch.as_tensor(index.class_stats.weights) if index.class_stats else None
    losses = LossComputer(cfg, model_cfg, weights)
    times = []
    for step in range(steps + 1):
        batch = collate([data[(step % len(data), step)]])
        t0 = time.perf_counter()
        out = model(batch["images"], batch["intrinsics"], batch["cam2ego"])
        loss = losses(out, batch, torch.device("cpu"), torch.Generator().manual_seed(step))["loss"]
        model.zero_grad(set_to_none=True)
        loss.backward()
        times.append(time.perf_counter() - t0)
    return {"recipe": name, "s_per_step": float(np.median(times[1:])), "rays": rays,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataroot", required=True)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--recipes", default="recommended,paper", help="recipe names (`occflownet recipes`)")
    add_jsonl_option(ap)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(one(args.dataroot, args.child, args.steps, args.rays)))
        return 0
    results = Results("bench_train_step", args.jsonl)
    print(f"tiny preset, {args.rays} rays, median of {args.steps} steps after one warm-up step")
    print("| recipe | s/step | peak RSS MB | machine |\n|---|---|---|---|")
    for name in args.recipes.split(","):
        res = subprocess.run([*module_argv(__spec__.name), "--dataroot", args.dataroot, "--steps", str(args.steps),
                              "--rays", str(args.rays), "--child", name], capture_output=True, text=True,
                             env=tree_env())
        if res.returncode:
            print(f"{name}: failed\n{res.stderr[-2000:]}", flush=True)
            continue
        r = json.loads(res.stdout.strip().splitlines()[-1])
        results.add(r, f"| {r['recipe']} | {r['s_per_step']:.2f} | {r['peak_rss_mb']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
