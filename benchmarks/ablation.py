"""The synthetic ablation study: the paper's component ladder on the synthetic world, one budget per row (rows 8, 9
add free-space beams, beyond the paper).

Usage (the data first, once):
    occflownet synth --out W/train --scenes 8 --frames 40 --seed 0 && occflownet prepare --dataroot W/train
    occflownet synth --out W/val --scenes 2 --frames 40 --seed 1000 && occflownet prepare --dataroot W/val
    python benchmarks/ablation.py --train W/train --val W/val --out W/runs --steps 200 [--rows 1,2,...]

Every row trains `tiny` with the same seed and step budget on split `all` of the train root, evaluates the EMA
checkpoint on split `all` of the val root (mIoU with the camera mask, RayIoU, static/dynamic mIoU) and appends a
JSON line to ``<out>/results.jsonl``; the table is printed at the end (markdown, for docs/ablation.md).
Rows already in results.jsonl are skipped, so the study can be resumed.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

# name → extra `occflownet train` options (the paper's Tables 1, 2 and 4 as issue 6 lists them)
ROWS = {
    1: ("3d (voxel labels only)", ["--supervision", "3d", "--horizon", "0", "--no-flow"]),
    2: ("2d, semantics only, O=0", ["--supervision", "2d", "--horizon", "0", "--no-depth-loss", "--no-dynamic-filter",
                                    "--no-disocclusion", "--no-loss-weighting", "--no-flow"]),
    3: ("2d, semantics + depth, O=0", ["--supervision", "2d", "--horizon", "0", "--no-dynamic-filter",
                                       "--no-disocclusion", "--no-loss-weighting", "--no-flow"]),
    4: ("2d, + temporal O=3, no filter", ["--supervision", "2d", "--horizon", "3", "--no-dynamic-filter",
                                          "--no-disocclusion", "--no-loss-weighting", "--no-flow"]),
    5: ("2d base: + filter, disocclusion, LW", ["--supervision", "2d", "--horizon", "3", "--no-flow"]),
    6: ("2d + flow", ["--supervision", "2d", "--horizon", "3", "--flow"]),
    7: ("2d+3d + flow", ["--supervision", "2d+3d", "--horizon", "3", "--flow"]),
    # beyond the paper: LiDAR beams without a return as free-space supervision (data/free_space.py)
    8: ("2d base + free space", ["--supervision", "2d", "--horizon", "3", "--no-flow", "--free-space"]),
    9: ("2d + flow + free space", ["--supervision", "2d", "--horizon", "3", "--flow", "--free-space"]),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", required=True)
    ap.add_argument("--val", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rows", default=",".join(map(str, ROWS)))
    ap.add_argument("--num-workers", type=int, default=1)
    ap.add_argument("--phase", choices=["train", "eval", "all"], default="all",
                    help="train only (e.g. several row groups in parallel), eval only, or both per row")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / "results.jsonl"
    done = {json.loads(line)["row"] for line in results_path.read_text().splitlines()} if results_path.exists() else set()
    for row in [int(r) for r in args.rows.split(",")]:
        if row in done:
            continue
        name, extra = ROWS[row]
        run = out / f"row{row}"
        train = [sys.executable, "-m", "occflownet", "train", "--preset", "tiny", "--dataroot", args.train,
                 "--split", "all", "--out", str(run), "--max-steps", str(args.steps), "--rays-per-step",
                 str(args.rays), "--seed", str(args.seed), "--num-workers", str(args.num_workers), "--quiet",
                 "--resume", *extra]
        if args.phase in ("train", "all"):
            t0 = time.time()
            print(f"row {row}: {name}\n  {' '.join(train)}", file=sys.stderr, flush=True)
            subprocess.run(train, check=True)
            (run / "train_seconds.txt").write_text(f"{time.time() - t0:.1f}")
        if args.phase == "train":
            continue
        t_train = float((run / "train_seconds.txt").read_text())
        predictions = run / "val_predictions"
        evaluate = [sys.executable, "-m", "occflownet", "eval", "--checkpoint", str(run / "checkpoints" / "last.pt"),
                    "--dataroot", args.val, "--split", "all", "--save-predictions", str(predictions)]
        res = subprocess.run(evaluate, check=True, capture_output=True, text=True)
        metrics = json.loads(res.stdout)
        record = {"row": row, "name": name, "options": extra, "steps": args.steps, "rays": args.rays,
                  "train_seconds": round(t_train, 1), "metrics": metrics, "density": density_stats(predictions)}
        shutil.rmtree(predictions)
        with open(results_path, "a") as f:
            f.write(json.dumps(record) + "\n")
    if results_path.exists():
        print(table(results_path))
    return 0


def density_stats(predictions: Path, tau: float = 0.35) -> dict:
    """σ over every voxel of every saved validation prediction: quantiles and the fraction at or above τ (the
    fusion threshold of a 2D-trained model), and the fraction the model calls occupied. Shows whether a row that
    scores 0 has learned no geometry or only not yet crossed τ."""
    import numpy as np

    from occflownet.occ3d import FREE

    files = sorted(predictions.glob("*.npz"))
    densities, occupied = [], 0
    for f in files:
        with np.load(f) as saved:
            densities.append(saved["density"].ravel())
            occupied += int(np.count_nonzero(saved["occupancy"] != FREE))
    density = np.concatenate(densities)
    occupied = occupied / density.size
    q = np.quantile(density, [0.5, 0.99, 0.999])
    return {"samples": len(files), "median": float(q[0]), "p99": float(q[1]), "p999": float(q[2]),
            "max": float(density.max()), "frac_ge_tau": float(np.mean(density >= tau)), "tau": tau,
            "frac_occupied": float(occupied)}


def _ratio(x):
    return "n/a" if x is None else f"{x:.2f}"


def _pct(x):
    return "n/a" if x is None else f"{100 * x:.2f}"


def table(results_path: Path) -> str:
    rows = sorted((json.loads(line) for line in results_path.read_text().splitlines()), key=lambda r: r["row"])
    lines = ["| # | setting | mIoU (cam mask) | RayIoU | static mIoU | dynamic mIoU | mIoU (no mask) | train s |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m = r["metrics"]
        occ = m["occupancy"]["camera_mask"]
        ray = m.get("rayiou") or {}
        lines.append(f"| {r['row']} | {r['name']} | {_pct(occ['miou'])} | {_pct(ray.get('rayiou'))} | "
                     f"{_pct(occ['miou_static'])} | {_pct(occ['miou_dynamic'])} | "
                     f"{_pct(m['occupancy']['all_voxels']['miou'])} | {r['train_seconds']:.0f} |")
    shown = ("driveable_surface", "sidewalk", "terrain", "manmade", "car", "truck")
    lines += ["", "| # | geometry IoU | " + " | ".join(shown) + " |", "|---|---|" + "---|" * len(shown)]
    for r in rows:
        occ = r["metrics"]["occupancy"]["camera_mask"]
        per_class = occ["iou_per_class"]
        lines.append(f"| {r['row']} | {_pct(occ['geometry_iou'])} | "
                     + " | ".join(_pct(per_class.get(name)) for name in shown) + " |")
    lines += ["", "Fog inside mask_camera (eval's `fog`: predicted occupied / labelled occupied voxels; crossed = some "
              "training ray of t ∈ [-3, 3] passes through the voxel):", "",
              "| # | labelled occupied | predicted occupied | fog factor | crossed: factor | never crossed: factor | "
              "never crossed: false positives |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        fog = r["metrics"].get("fog")
        if fog:
            cam, crossed, never = fog["camera_mask"], fog["crossed"], fog["never_crossed"]
            lines.append(f"| {r['row']} | {_pct(cam['labelled_fraction'])} % | {_pct(cam['predicted_fraction'])} % | "
                         f"{_ratio(cam['fog_factor'])} | {_ratio(crossed['fog_factor'])} | "
                         f"{_ratio(never['fog_factor'])} | {never['false_positive']} |")
    lines += ["", "σ over all voxels of the grid (inside and outside the camera mask):", "",
              "| # | σ median | σ p99 | σ p99.9 | σ max | voxels σ ≥ 0.35 | predicted occupied |",
              "|---|---|---|---|---|---|---|"]
    for r in rows:
        d = r.get("density")
        if d:
            lines.append(f"| {r['row']} | {d['median']:.3f} | {d['p99']:.3f} | {d['p999']:.3f} | {d['max']:.3f} | "
                         f"{100 * d['frac_ge_tau']:.2f} % | {100 * d['frac_occupied']:.2f} % |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
