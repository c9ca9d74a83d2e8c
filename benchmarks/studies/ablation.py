"""The synthetic ablation study: the paper's component ladder on the synthetic world, one budget per row (rows 8, 9
add free-space beams, beyond the paper).

Usage (the data first, once):
    occflownet synth --out W/train --scenes 8 --frames 40 --seed 0 && occflownet prepare --dataroot W/train
    occflownet synth --out W/val --scenes 2 --frames 40 --seed 1000 && occflownet prepare --dataroot W/val
    python benchmarks/ablation.py --train W/train --val W/val --out W/runs --steps 200 [--rows 1,2,...] \
        [--seed S] [--extra "OPTIONS"]

Every row trains `tiny` with the same seed and step budget on split `all` of the train root, evaluates the EMA
checkpoint on split `all` of the val root (mIoU with the camera mask, RayIoU, static/dynamic mIoU) and appends a
JSON line to ``<out>/results.jsonl``; the table is printed at the end (markdown, for docs/results.md).
Rows already in results.jsonl are skipped, so the study can be resumed (one ``--out`` per seed and per ``--extra``:
the records are keyed by row). ``--extra`` adds the same ``occflownet train`` options to every row.
"""
from __future__ import annotations

import argparse
import json
import shlex
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


def train_row(train_root, run: Path, row: int, steps: int, seed: int, rays: int, num_workers: int = 1,
              extra: tuple[str, ...] = ()) -> float:
    """Train row ``row`` of ROWS to ``steps`` in ``run`` (resuming what is there; the learning rate is constant
    after warm-up, so resuming to a larger budget continues the same run); returns the seconds this call took."""
    train = [sys.executable, "-m", "occflownet", "train", "--preset", "tiny", "--dataroot", str(train_root),
             "--split", "all", "--out", str(run), "--max-steps", str(steps), "--rays-per-step", str(rays), "--seed",
             str(seed), "--num-workers", str(num_workers), "--quiet", "--resume", *ROWS[row][1], *extra]
    t0 = time.time()
    print(f"row {row} ({ROWS[row][0]}), seed {seed}, to {steps} steps\n  {' '.join(train)}", file=sys.stderr,
          flush=True)
    subprocess.run(train, check=True)
    return time.time() - t0


def evaluate_row(val_root, run: Path) -> dict:
    """{"metrics": the eval JSON of the run's last checkpoint on split 'all' of ``val_root``, "density": σ figures,
    "geometry_by_tau": geometry IoU inside mask_camera at several τ}."""
    predictions = run / "val_predictions"
    evaluate = [sys.executable, "-m", "occflownet", "eval", "--checkpoint", str(run / "checkpoints" / "last.pt"),
                "--dataroot", str(val_root), "--split", "all", "--save-predictions", str(predictions)]
    res = subprocess.run(evaluate, check=True, capture_output=True, text=True)
    out = {"metrics": json.loads(res.stdout), "density": density_stats(predictions),
           "geometry_by_tau": geometry_by_tau(predictions, val_root)}
    shutil.rmtree(predictions)
    return out


def done_rows(results_path: Path) -> set:
    """(row, seed, steps) of the records already in a results.jsonl."""
    if not results_path.exists():
        return set()
    return {(r["row"], r.get("seed", 0), r["steps"]) for r in map(json.loads, results_path.read_text().splitlines())}


def append(results_path: Path, record: dict) -> None:
    """Append one JSON line; an exclusive lock keeps lines whole when several studies share the file."""
    import fcntl

    with open(results_path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        f.write(json.dumps(record) + "\n")


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
    ap.add_argument("--extra", default="", help="extra `occflownet train` options for every row (one string, e.g. "
                                                "the recommended 2D recipe of docs/training.md)")
    ap.add_argument("--phase", choices=["train", "eval", "all"], default="all",
                    help="train only (e.g. several row groups in parallel), eval only, or both per row")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / "results.jsonl"
    done = {row for row, _, _ in done_rows(results_path)}
    extra = tuple(shlex.split(args.extra))
    for row in [int(r) for r in args.rows.split(",")]:
        if row in done:
            continue
        run = out / f"row{row}"
        if args.phase in ("train", "all"):
            seconds = train_row(args.train, run, row, args.steps, args.seed, args.rays, args.num_workers, extra)
            (run / "train_seconds.txt").write_text(f"{seconds:.1f}")
        if args.phase == "train":
            continue
        t_train = float((run / "train_seconds.txt").read_text())
        append(results_path, {"row": row, "name": ROWS[row][0], "options": ROWS[row][1] + list(extra),
                              "steps": args.steps, "rays": args.rays, "seed": args.seed,
                              "train_seconds": round(t_train, 1),
                              **evaluate_row(args.val, run)})
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


TAUS = (0.02, 0.05, 0.1, 0.2, 0.35, 0.5, 0.7)


def geometry_by_tau(predictions: Path, root, taus=TAUS) -> dict:
    """{str(τ): geometry IoU inside mask_camera over all saved predictions (σ ≥ τ against labels != free)}, for the
    keyframes of ``root`` whose ``<token>.npz`` is in ``predictions``. Tells whether a row that scores 0 at its own
    τ has learned the geometry at another level of σ (the opacity reading, for one, needs a lower σ for the same
    fog)."""
    import numpy as np

    from occflownet.data.index import load_index
    from occflownet.data.loaders import load_occupancy
    from occflownet.occ3d import FREE

    index = load_index(root, None, check_tables=False)
    inter = np.zeros(len(taus))
    union = np.zeros(len(taus))
    for p in range(len(index)):
        sample = index[p]
        path = predictions / f"{sample.token}.npz"
        if not path.is_file():
            continue
        labels = load_occupancy(root, sample.occupancy_path)
        mask = labels.mask_camera.astype(bool)
        truth = (labels.semantics != FREE)[mask]
        with np.load(path) as saved:
            density = saved["density"][mask]
        for i, tau in enumerate(taus):
            pred = density >= tau
            inter[i] += np.count_nonzero(pred & truth)
            union[i] += np.count_nonzero(pred | truth)
    return {str(t): float(inter[i] / union[i]) if union[i] else None for i, t in enumerate(taus)}


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
