"""The quickstart's stage costs on this machine: runs ``occflownet quickstart`` (or reads the ``timings.json`` of a
finished one) and prints each stage's seconds per unit of work beside this machine's matmul rate, as the
``StageCosts`` that ``occflownet/quickstart.py`` scales into the estimate it prints at the start.

    python -m benchmarks.perf.bench_quickstart --out /tmp/qs [--reuse] [--jsonl PATH] [quickstart options ...]

``--reuse``: do not run; read ``OUT/timings.json`` and ``OUT/run/log.jsonl`` of a quickstart that ran on this
machine. Steps are counted from the run's log (the time limit may stop training before ``--max-steps``). Prints
one JSON object: the recipe, the float32 matmul rate (1024³, torch's threads, measured over 2 s after the run),
the stage costs (``StageCosts``' fields, and ``train_per_step``: the recipe's ``step_seconds`` here) and the
validation scores in % (mIoU, geometry IoU, car IoU, RayIoU inside mask_camera), followed by the
load average; the same record is appended to ``--jsonl``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from benchmarks.harness import Results, add_jsonl_option
from occflownet.quickstart import QuickstartConfig


def stage_costs(out: Path) -> dict:
    """{field of StageCosts: value} from a finished quickstart folder (timings.json, run/log.jsonl), with the
    seconds of a training step of its recipe ("train_per_step": the recipe's ``step_seconds`` on this machine) and
    the steps trained."""
    timings = json.loads((out / "timings.json").read_text())
    seconds, cfg = timings["seconds"], timings["config"]
    log = [json.loads(line) for line in (out / "run" / "log.jsonl").read_text().splitlines()]
    keyframes = cfg["scenes"] * cfg["frames"]
    first, last = log[0], log[-1]                     # steps/s between the first and the last log record
    per_step = (last["time"] - first["time"]) / max(1, last["step"] - first["step"])
    return {"synth_per_keyframe": seconds["synth"] / keyframes, "prepare_per_keyframe": seconds["prepare"] / keyframes,
            "train_setup": max(0.0, seconds["train"] - per_step * last["step"]),
            "train_per_step": per_step,
            "eval_per_keyframe": seconds["eval"] / cfg["frames"], "export": seconds["export"], "steps": last["step"]}


def val_scores(out: Path) -> dict:
    """The figures the README quotes, in %, from a finished quickstart's eval.json (inside mask_camera)."""
    result = json.loads((out / "eval.json").read_text())
    occupancy = result["occupancy"]["camera_mask"]
    scores = {"miou": occupancy["miou"], "geometry_iou": occupancy["geometry_iou"],
              "car": occupancy["iou_per_class"]["car"], "rayiou": result["rayiou"]["rayiou"]}
    return {k: round(100 * v, 2) for k, v in scores.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--reuse", action="store_true")
    add_jsonl_option(p)
    args, rest = p.parse_known_args(argv)
    out = Path(args.out)
    if not args.reuse:
        subprocess.run([sys.executable, "-m", "occflownet", "quickstart", "--out", str(out), *rest], check=True)
    results = Results("bench_quickstart", args.jsonl, matmul_seconds=2.0)
    state = results.state()
    costs = {"matmul_gflops": state["matmul_gflops"], **stage_costs(out)}
    recipe = QuickstartConfig(**json.loads((out / "timings.json").read_text())["config"]).recipe
    record = {"recipe": recipe} | {k: round(v, 3) for k, v in costs.items()} | {"scores": val_scores(out)}
    results.add(record, json.dumps(record, indent=1), state)
    return 0


if __name__ == "__main__":
    sys.exit(main())
