"""The fitting protocol: can a supervision fit the world it trains on? Rows of the ablation ladder
(``benchmarks/ablation.py`` ROWS) trained on split ``all`` of one fresh 1 scene × 8 keyframe world and scored on the
same keyframes, continued with ``--resume`` through growing budgets (the learning rate is constant after warm-up),
for several seeds. The first thing to run after any change to rendering, losses, sampling or the model.

    export OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1
    python benchmarks/fitting.py --out DIR [--rows 1,5] [--seeds 0,1] [--budgets 200,800,2000] [--world-seed 101]
    python benchmarks/fitting.py --out DIR --rows 5 --variant opacity --extra "--sigma-is opacity"

Writes ``DIR/world`` (unless ``--world`` names one), the runs ``DIR/seed<S>/row<R>`` and one JSON line per (row,
seed, budget) to ``DIR/results.jsonl`` as each evaluation finishes (a stopped study resumes: finished records are
skipped, runs resume from their checkpoints; several invocations with other ``--rows``/``--seeds``/``--variant``
may share DIR). ``--variant NAME --extra "OPTIONS"`` trains the rows with extra ``occflownet train`` options, in
``DIR/NAME/seed<S>/row<R>``, recorded under that name (default ``official``: the rows as ``ablation.ROWS`` has them).
Prints the tables: per record mIoU, geometry IoU, fog factors inside mask_camera (all, where training rays cross,
where none does), per-class IoU; and the ratio of ``--ratio A/B`` rows (default 5/1: the 2D base against 3D labels).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import shlex

from ablation import ROWS, append, evaluate_row, train_row

CLASSES = ("car", "bus", "truck", "manmade", "vegetation", "driveable_surface", "sidewalk", "terrain")


def make_world(world: Path, seed: int) -> None:
    if not (world / "gts" / "labels.json").is_file():
        subprocess.run([sys.executable, "-m", "occflownet", "synth", "--out", str(world), "--scenes", "1", "--frames",
                        "8", "--seed", str(seed), "--no-progress", "--overwrite"], check=True)
    if not (world / "occflownet").is_dir():
        subprocess.run([sys.executable, "-m", "occflownet", "prepare", "--dataroot", str(world), "--quiet"], check=True)


OFFICIAL = "official"


def _records(results: Path) -> list[dict]:
    return list(map(json.loads, results.read_text().splitlines())) if results.exists() else []


def _key(record: dict) -> tuple:
    return record.get("variant", OFFICIAL), record["row"], record["seed"], record["steps"]


def run_chain(world: Path, out: Path, row: int, seed: int, budgets: list[int], rays: int, results: Path,
              variant: str = OFFICIAL, extra: tuple[str, ...] = ()) -> None:
    run = (out if variant == OFFICIAL else out / variant) / f"seed{seed}" / f"row{row}"
    seconds = 0.0
    for steps in budgets:
        if (variant, row, seed, steps) in {_key(r) for r in _records(results)}:
            continue
        seconds += train_row(world, run, row, steps, seed, rays, num_workers=0, extra=extra)
        append(results, {"variant": variant, "row": row, "name": ROWS[row][0], "options": ROWS[row][1] + list(extra),
                         "seed": seed, "steps": steps, "rays": rays, "train_seconds": round(seconds, 1),
                         **evaluate_row(world, run)})


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


def tables(results: Path, ratio: tuple[int, int]) -> str:
    records = sorted(_records(results), key=lambda r: (r["steps"], r["row"], r.get("variant", OFFICIAL), r["seed"]))
    lines = ["| steps | row | variant | seed | mIoU | geometry IoU | at best τ | fog (mask_camera) | fog (crossed) | fog (never crossed) | "
             + " | ".join(CLASSES) + " |", "|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(CLASSES)]
    for r in records:
        cam = r["metrics"]["occupancy"]["camera_mask"]
        lines.append(f"| {r['steps']} | {r['row']} | {r.get('variant', OFFICIAL)} | {r['seed']} | {_pct(cam['miou'])} | {_pct(cam['geometry_iou'])} | "
                     f"{_best_tau(r)} | {_fog(r, 'camera_mask')} | {_fog(r, 'crossed')} | {_fog(r, 'never_crossed')} | "
                     + " | ".join(_pct(cam["iou_per_class"].get(c)) for c in CLASSES) + " |")
    by = {_key(r): r["metrics"]["occupancy"]["camera_mask"] for r in records}
    a, b = ratio
    lines += ["", f"| steps | variant of row {a} | seed | row {a} ÷ official row {b} (mIoU) | (geometry IoU) |",
              "|---|---|---|---|---|"]
    for (variant, row, seed, steps), cam in sorted(by.items(), key=lambda kv: (kv[0][3], kv[0][0], kv[0][2])):
        other = by.get((OFFICIAL, b, seed, steps))
        if row == a and other and other["miou"] and other["geometry_iou"]:
            lines.append(f"| {steps} | {variant} | {seed} | {cam['miou'] / other['miou']:.2f} | "
                         f"{cam['geometry_iou'] / other['geometry_iou']:.2f} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--world", default=None, help="an existing prepared root (default: OUT/world, made if missing)")
    ap.add_argument("--world-seed", type=int, default=101, help="seed of the fresh world (held out from tuning)")
    ap.add_argument("--rows", default="1,5")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--budgets", default="200,800,2000")
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--ratio", default="5/1", help="rows A/B whose mIoU and geometry ratio is tabled")
    ap.add_argument("--variant", default=OFFICIAL, help="name under which runs with --extra options are recorded")
    ap.add_argument("--extra", default="", help="extra `occflownet train` options of the variant (one string)")
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results.jsonl"
    if args.variant == OFFICIAL and args.extra:
        ap.error("--extra needs a --variant name other than 'official'")
    if not args.table_only:
        world = Path(args.world) if args.world else out / "world"
        if not args.world:
            make_world(world, args.world_seed)
        budgets = sorted(int(b) for b in args.budgets.split(","))
        for seed in (int(s) for s in args.seeds.split(",")):
            for row in (int(r) for r in args.rows.split(",")):
                run_chain(world, out, row, seed, budgets, args.rays, results, args.variant,
                          tuple(shlex.split(args.extra)))
    if results.exists():
        print(tables(results, tuple(int(v) for v in args.ratio.split("/"))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
