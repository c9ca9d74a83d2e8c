"""Model cost on this CPU: tiny forward+backward (training step shape), and one forward of larger presets.

    python -m benchmarks.perf.bench_model [--cases tiny-train base-forward paper-forward] [--steps 5] [--jsonl PATH]

Each case runs in its own child process so that its peak RSS (resource.ru_maxrss) is its own.
- ``tiny-train``: batch 1 (six 480x270 images, the synthetic world's size), forward + backward of a loss touching
  every output (density, logits, depth_prob), ``--steps`` timed steps after one warm-up; parameter count.
- ``base-forward`` / ``paper-forward``: one no-grad ``forward`` at batch 1 (the reduced batch) from six 1600x900
  images, timed once after building.
Prints per case the parameter count, the time and the peak resident memory, with the load average and the float32
matmul rate (appended to ``--jsonl``).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

from benchmarks.harness import Results, add_jsonl_option, module_argv, tree_env


def _inputs(width: int, height: int, batch: int = 1):
    import torch

    from occflownet.contract import calibration_arrays
    from occflownet.rig import default_rig

    K, T = calibration_arrays(default_rig(width, height))
    g = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (batch, 6, height, width, 3), dtype=torch.uint8, generator=g)
    return images, torch.from_numpy(K)[None].repeat(batch, 1, 1, 1), torch.from_numpy(T)[None].repeat(batch, 1, 1, 1)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_case(case: str, steps: int) -> dict:
    import torch

    from occflownet.model import create_model, get_preset

    torch.set_num_threads(os.cpu_count() or 1)
    preset, kind = case.split("-")
    t = time.perf_counter()
    model = create_model(get_preset(preset), seed=0)
    build_s = time.perf_counter() - t
    params = sum(p.numel() for p in model.parameters())
    rss_built = _peak_rss_mb()
    if kind == "train":
        model.train()
        args = _inputs(480, 270)
        times = []
        for i in range(steps + 1):
            t = time.perf_counter()
            out = model(*args)
            loss = out["density"].mean() + out["logits"].logsumexp(-1).mean() + out["depth_prob"].square().mean()
            loss.backward()
            model.zero_grad(set_to_none=True)
            if i:
                times.append(time.perf_counter() - t)
        times.sort()
        return {"case": case, "params_M": params / 1e6, "build_s": build_s, "step_p50_s": times[len(times) // 2],
                "step_min_s": times[0], "peak_rss_mb": _peak_rss_mb(), "rss_after_build_mb": rss_built}
    model.eval()
    args = _inputs(1600, 900)
    with torch.no_grad():
        t = time.perf_counter()
        out = model(*args)
        forward_s = time.perf_counter() - t
    assert out["density"].shape == (1, 200, 200, 16)
    return {"case": case, "params_M": params / 1e6, "build_s": build_s, "forward_s": forward_s,
            "peak_rss_mb": _peak_rss_mb(), "rss_after_build_mb": rss_built}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="+", default=["tiny-train", "paper-forward"],
                   choices=["tiny-train", "base-train", "tiny-forward", "base-forward", "paper-forward"])
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--child", help=argparse.SUPPRESS)
    add_jsonl_option(p)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(run_case(args.child, args.steps)))
        return 0
    results = Results("bench_model", args.jsonl)
    print(f"cpu cores {os.cpu_count()}")
    for case in args.cases:
        proc = subprocess.run([*module_argv(__spec__.name), "--child", case, "--steps", str(args.steps)],
                              capture_output=True, text=True, env=tree_env())
        if proc.returncode:
            print(f"{case}: FAILED\n{proc.stderr[-2000:]}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        timing = (f"forward+backward p50 {r['step_p50_s'] * 1e3:.0f} ms (min {r['step_min_s'] * 1e3:.0f})"
                  if "step_p50_s" in r else f"one forward {r['forward_s']:.1f} s")
        results.add(r, f"{case}: {r['params_M']:.2f} M params, {timing}, peak RSS {r['peak_rss_mb']:.0f} MB "
                       f"(after build {r['rss_after_build_mb']:.0f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
