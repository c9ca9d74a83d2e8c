"""Time and peak memory of one `tiny` training step (data excluded), per configuration, each in its own process.

    python benchmarks/bench_train_step.py --dataroot W [--steps 5] [--rays 4096] [--configs base,flow,3d]

W is a prepared root (`occflownet prepare`). Prints seconds per step (forward, losses incl. rendering/warp,
backward; median of --steps after one warm-up step) and the peak resident memory of the process.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

CONFIGS = {
    "base": dict(supervision="2d", horizon=3, flow=False),           # filter + disocclusion + loss weighting
    "flow": dict(supervision="2d", horizon=3, flow=True),
    "3d": dict(supervision="3d", horizon=0, flow=False),
    "2d+3d+flow": dict(supervision="2d+3d", horizon=3, flow=True),
}


def one(dataroot: str, name: str, steps: int, rays: int) -> dict:
    import numpy as np
    import torch

    from occflownet.data.flow import flow_path, load_flow_records
    from occflownet.data.index import load_index
    from occflownet.model import create_model, get_preset
    from occflownet.train.recipe import TrainConfig
    from occflownet.train.dataset import TrainingSamples, collate
    from occflownet.train.step import LossComputer

    cfg = TrainConfig(dataroot=dataroot, split="all", rays_per_step=rays, **CONFIGS[name])
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
    return {"config": name, "s_per_step": float(np.median(times[1:])), "rays": rays,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataroot", required=True)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--configs", default="base,flow")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(one(args.dataroot, args.child, args.steps, args.rays)))
        return 0
    print(f"{'config':<12} {'s/step':>8} {'peak RSS MB':>12}")
    for name in args.configs.split(","):
        res = subprocess.run([sys.executable, __file__, "--dataroot", args.dataroot, "--steps", str(args.steps),
                              "--rays", str(args.rays), "--child", name], capture_output=True, text=True, check=True)
        r = json.loads(res.stdout.strip().splitlines()[-1])
        print(f"{r['config']:<12} {r['s_per_step']:>8.2f} {r['peak_rss_mb']:>12.0f}")
    import os

    print(f"(tiny preset, {args.rays} rays, median of {args.steps} steps; load average {os.getloadavg()[0]:.1f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
