"""The fitting protocol: can a supervision fit the world it trains on? Recipes (by name, or rows of the paper's
ablation ladder) trained on split ``all`` of one fresh 1 scene × 8 keyframe world and scored on the same keyframes,
continued with ``--resume`` through growing budgets (the learning rate is constant after warm-up), for several
seeds. The first thing to run after any change to rendering, losses, sampling or the model.

    export OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1
    python -m benchmarks.studies.fitting --out F --recipes recommended,paper-3d --seeds 0,1 --budgets 200,800,2000
    python -m benchmarks.studies.fitting --out F --rows 5 --rendering --seeds 0,1
    python -m benchmarks.studies.fitting --out F --recipes recommended --variant fp32 --extra "--precision fp32"

The runs are selected as in ``benchmarks/studies/ablation.py`` (``--recipes`` names, default ``recommended,paper-3d``;
``--rows`` of ``recipes.ladder()``; ``--rendering`` adds ``recipes.RENDERING`` to the runs that render rays, recorded
as variant ``rendering``; ``--variant NAME --extra "OPTIONS"`` adds ``occflownet train`` options, recorded under
NAME). Writes ``F/world`` (synth ``--world-seed``, unless ``--world`` names a prepared root), the runs
``F/VARIANT/seed<S>/RECIPE`` and one JSON line per (variant, recipe, seed, budget) to ``F/results.jsonl`` as each
evaluation finishes (a stopped study resumes: recorded budgets are skipped, runs resume from their checkpoints;
several invocations with other recipes, seeds or variants may share F). Prints the tables: per record mIoU, geometry
IoU (and at its best τ), fog factors inside mask_camera (all, where training rays cross, where none does), per-class
IoU; and the mIoU and geometry ratios of ``--ratio A/B`` (default ``recommended/paper-3d``: each variant of recipe A
against recipe B as registered, same seed and budget).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from benchmarks.harness import append_jsonl, read_jsonl
from benchmarks.studies.ablation import (RECIPE_VARIANT, add_run_options, evaluate_run, record_key, run_folder,
                                         run_record, selected_runs, train_run)

CLASSES = ("car", "bus", "truck", "manmade", "vegetation", "driveable_surface", "sidewalk", "terrain")
DEFAULT_RECIPES = "recommended,paper-3d"


def make_world(world: Path, seed: int) -> None:
    if not (world / "gts" / "labels.json").is_file():
        subprocess.run([sys.executable, "-m", "occflownet", "synth", "--out", str(world), "--scenes", "1", "--frames",
                        "8", "--seed", str(seed), "--no-progress", "--overwrite"], check=True)
    if not (world / "occflownet").is_dir():
        subprocess.run([sys.executable, "-m", "occflownet", "prepare", "--dataroot", str(world), "--quiet"], check=True)


def run_chain(world: Path, out: Path, run, seed: int, budgets: list[int], rays: int, results: Path) -> None:
    """Train ``run`` through ``budgets`` (resuming), appending each budget's evaluation to ``results``."""
    folder = run_folder(out, run, seed)
    seconds = 0.0
    for steps in budgets:
        if (run.variant, run.recipe, seed, steps) in {record_key(r) for r in read_jsonl(results)}:
            continue
        seconds += train_run(world, folder, run, steps, seed, rays, num_workers=0)
        append_jsonl(results, {**run_record(run, seed, steps, rays, seconds), **evaluate_run(world, folder)})


def _pct(x) -> str:
    return "n/a" if x is None else f"{100 * x:.1f}"


def _fog(record: dict, part: str) -> str:
    fog = record["metrics"].get("fog") or {}
    value = (fog.get(part) or {}).get("fog_factor")
    return "n/a" if value is None else f"{value:.2f}"


def _best_tau(record: dict) -> str:
    by = {float(t): v for t, v in (record.get("geometry_by_tau") or {}).items() if v is not None}
    if not by:
        return "n/a"
    tau = max(by, key=by.get)
    return f"{100 * by[tau]:.1f} ({tau:g})"


def tables(results: Path, ratio: tuple[str, str]) -> str:
    records = sorted(read_jsonl(results), key=lambda r: (r["steps"], *record_key(r)))
    lines = ["| steps | recipe | variant | seed | mIoU | geometry IoU | at best τ | fog (mask_camera) | "
             "fog (crossed) | fog (never crossed) | " + " | ".join(CLASSES) + " |",
             "|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(CLASSES)]
    for r in records:
        variant, recipe, seed, steps = record_key(r)
        cam = r["metrics"]["occupancy"]["camera_mask"]
        lines.append(f"| {steps} | {recipe} | {variant} | {seed} | {_pct(cam['miou'])} | {_pct(cam['geometry_iou'])} | "
                     f"{_best_tau(r)} | {_fog(r, 'camera_mask')} | {_fog(r, 'crossed')} | {_fog(r, 'never_crossed')} | "
                     + " | ".join(_pct(cam["iou_per_class"].get(c)) for c in CLASSES) + " |")
    by = {record_key(r): r["metrics"]["occupancy"]["camera_mask"] for r in records}
    a, b = ratio
    lines += ["", f"| steps | variant of {a} | seed | {a} ÷ {b} (mIoU) | (geometry IoU) |", "|---|---|---|---|---|"]
    for (variant, recipe, seed, steps), cam in sorted(by.items(), key=lambda kv: (kv[0][3], kv[0][0], kv[0][2])):
        other = by.get((RECIPE_VARIANT, b, seed, steps))
        if recipe == a and other and other["miou"] and other["geometry_iou"]:
            lines.append(f"| {steps} | {variant} | {seed} | {cam['miou'] / other['miou']:.2f} | "
                         f"{cam['geometry_iou'] / other['geometry_iou']:.2f} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--world", default=None, help="an existing prepared root (default: OUT/world, made if missing)")
    ap.add_argument("--world-seed", type=int, default=101, help="seed of the fresh world (held out from tuning)")
    add_run_options(ap, DEFAULT_RECIPES)
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--budgets", default="200,800,2000")
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--ratio", default="recommended/paper-3d", help="recipes A/B whose mIoU and geometry ratio is "
                                                                    "tabled (A: every variant; B: as registered)")
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args()
    runs = selected_runs(ap, args, DEFAULT_RECIPES)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results.jsonl"
    if not args.table_only:
        world = Path(args.world) if args.world else out / "world"
        if not args.world:
            make_world(world, args.world_seed)
        budgets = sorted(int(b) for b in args.budgets.split(","))
        for seed in (int(s) for s in args.seeds.split(",")):
            for run in runs:
                run_chain(world, out, run, seed, budgets, args.rays, results)
    if results.exists():
        print(tables(results, tuple(args.ratio.split("/", 1))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
