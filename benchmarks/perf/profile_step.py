"""Where a training step's time goes: data loading, each part of the network's forward pass, the losses (rendering
included), the backward pass, the optimizer and the EMA, for one preset and recipe, in the real loop.

    export OMP_NUM_THREADS=2 NUMBA_NUM_THREADS=2
    python -m benchmarks.perf.profile_step --dataroot W [--preset tiny] [--recipes paper-3d,paper,recommended]
        [--steps 6] [--num-workers 0] [--rays 4096] [--ops 12] [--by-shape] [--jsonl PATH]

W is a prepared root (`occflownet prepare`; the recipes with 3D labels need its Occ3D labels). A recipe is a name of
``occflownet/train/recipes.py`` (``TrainConfig.from_recipe``). Each recipe runs in its own process:
the training loop's own data loader, TrainingState and LossComputer, ``occflownet.train.loop.train_step`` for
``--steps`` steps after one warm-up step. Stages are timed with perf_counter (module forward hooks for the network's
parts, wrappers for the losses, the optimizer and the EMA; "backward and the rest" is the step minus the timed
parts); the torch.profiler table of the same steps lists the operators by self CPU time. "data" is the wait for the
next batch: with ``--num-workers 0`` the whole loading (images, rays, labels), with workers what they did not hide.
Prints per recipe a markdown table (seconds and share of each stage) with the load average and the float32 matmul
rate, then the operator table; appends the stage seconds to ``--jsonl``.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from collections import defaultdict

from benchmarks.harness import Results, add_jsonl_option, module_argv, tree_env
from occflownet.choices import PRECISIONS

PARTS = ("backbone", "neck", "depth_head", "lift", "decoder")


class StageClock:
    """Seconds per named stage, accumulated while ``active``."""

    def __init__(self):
        self.seconds = defaultdict(float)
        self.active = False
        self._start = {}

    def begin(self, name):
        self._start[name] = time.perf_counter()

    def end(self, name):
        if self.active:
            self.seconds[name] += time.perf_counter() - self._start[name]

    def timed(self, name, fn):
        def wrapper(*args, **kwargs):
            self.begin(name)
            try:
                return fn(*args, **kwargs)
            finally:
                self.end(name)
        return wrapper

    def hook_module(self, name, module):
        module.register_forward_pre_hook(lambda *_: self.begin(name))
        module.register_forward_hook(lambda *_: self.end(name))


class TimedCall:
    """``obj`` with its calls made through ``timed_call`` and every other attribute its own (the loop calls the
    LossComputer and also reads ``head_rows`` from it)."""

    def __init__(self, obj, timed_call):
        self._obj, self._timed_call = obj, timed_call

    def __call__(self, *args, **kwargs):
        return self._timed_call(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._obj, name)


def one(dataroot: str, preset: str, name: str, steps: int, num_workers: int, rays: int | None, ops: int,
        precision: str = "auto", by_shape: bool = False) -> dict:
    import torch
    from torch.profiler import ProfilerActivity, profile

    from occflownet.heap import reuse_freed_memory
    from occflownet.train import loop
    from occflownet.train.recipe import TrainConfig
    from occflownet.train.state import TrainingState
    from occflownet.train.step import LossComputer

    cfg = TrainConfig.from_recipe(name, preset=preset, dataroot=dataroot, split="all", out="/tmp/profile_step",
                                  rays_per_step=rays, num_workers=num_workers, max_steps=steps + 1, precision=precision)
    device = torch.device("cpu")
    reuse_freed_memory()                                         # as train() does
    index, positions, flows = loop._training_data(cfg)
    state = TrainingState.create(cfg, loop._model_config(cfg, index, positions), device)
    losses = LossComputer(cfg, state.model_cfg, loop._class_weights(cfg, index, device))
    clock = StageClock()
    clock.hook_module("forward", state.model)
    for part in PARTS:
        clock.hook_module(f"forward: {part}", getattr(state.model, part))
    losses_timed = TimedCall(losses, clock.timed("losses (rendering included)", losses))
    state.optimizer.step = clock.timed("optimizer", state.optimizer.step)
    state.ema.update = clock.timed("EMA", state.ema.update)
    generator = torch.Generator().manual_seed(0)
    amp = loop.autocast_dtype(device, cfg.precision)
    loop.float32_math(device, cfg.precision)
    batches = iter(loop._data_loader(cfg, index, positions, flows, 0, loop.ddp.DistInfo()))

    def step(n: int) -> None:
        clock.active = n > 0                 # the first step warms up (allocator, numba compilation, caches)
        clock.begin("data")
        batch = next(batches)
        clock.end("data")
        clock.begin("step")
        loop.train_step(state, state.model, losses_timed, batch, device, generator, amp)
        clock.end("step")

    step(0)
    with profile(activities=[ProfilerActivity.CPU], record_shapes=by_shape) as prof:
        for n in range(1, steps + 1):
            step(n)
    s = {k: v / steps for k, v in clock.seconds.items()}
    timed = sum(s[k] for k in ("forward", "losses (rendering included)", "optimizer", "EMA"))
    s["backward and the rest"] = s["step"] - timed
    s["forward: preprocessing and the rest"] = s["forward"] - sum(s[f"forward: {p}"] for p in PARTS)
    table = prof.key_averages(group_by_input_shape=by_shape).table(sort_by="self_cpu_time_total", row_limit=ops,
                                                                   max_name_column_width=40)
    return {"recipe": name, "preset": preset, "seconds": s, "amp": str(amp), "ops": table,
            "threads": torch.get_num_threads(), "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


ORDER = ("data", "forward: backbone", "forward: neck", "forward: depth_head", "forward: lift", "forward: decoder",
         "forward: preprocessing and the rest", "losses (rendering included)", "backward and the rest", "optimizer",
         "EMA")


def report(r: dict) -> str:
    s = r["seconds"]
    total = s["data"] + s["step"]
    lines = [f"## {r['preset']} {r['recipe']}: {total:.3f} s per step (data + step), {r['threads']} torch threads, "
             f"autocast {r['amp']}, peak RSS {r['peak_rss_mb']:.0f} MB", "", "| stage | s/step | share |",
             "|---|---|---|"]
    lines += [f"| {k} | {s[k]:.3f} | {100 * s[k] / total:.1f} % |" for k in ORDER]
    return "\n".join(lines + ["", r["ops"]])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataroot", required=True)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--recipes", default="paper-3d,paper,recommended", help="recipe names (`occflownet recipes`)")
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--num-workers", type=int, default=0)
    ap.add_argument("--rays", type=int, default=None, help="rays per step (default: the preset's)")
    ap.add_argument("--ops", type=int, default=12, help="rows of the operator table")
    ap.add_argument("--precision", default="auto", choices=PRECISIONS,
                    help="train --precision (auto: float32 on CPUs; bf16: autocast where the CPU computes it natively)")
    ap.add_argument("--by-shape", action="store_true", help="one operator row per input shape (record_shapes)")
    add_jsonl_option(ap)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(one(args.dataroot, args.preset, args.child, args.steps, args.num_workers, args.rays,
                             args.ops, precision=args.precision, by_shape=args.by_shape)))
        return 0
    results = Results("profile_step", args.jsonl)
    print(f"(mean of {args.steps} steps after one warm-up step, which the operator table leaves out too)")
    for name in args.recipes.split(","):
        cmd = [*module_argv(__spec__.name), "--dataroot", args.dataroot, "--preset", args.preset, "--steps",
               str(args.steps), "--num-workers", str(args.num_workers), "--ops", str(args.ops), "--child", name]
        if args.rays:
            cmd += ["--rays", str(args.rays)]
        cmd += ["--precision", args.precision] + (["--by-shape"] if args.by_shape else [])
        res = subprocess.run(cmd, capture_output=True, text=True, env=tree_env())
        if res.returncode != 0:
            print(f"## {args.preset} {name}: failed\n{res.stderr[-2000:]}")
            continue
        r = json.loads(res.stdout.strip().splitlines()[-1])
        head, _, body = report(r).partition("\n")
        results.add({k: v for k, v in r.items() if k != "ops"}, head)
        print(body, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
