"""The ablation study: recipes by name (by default the paper's component ladder) trained on a train world and
scored on a val world, one budget per run.

    occflownet synth --out W/train --scenes 8 --frames 40 --seed 0 && occflownet prepare --dataroot W/train
    occflownet synth --out W/val --scenes 2 --frames 40 --seed 1000 && occflownet prepare --dataroot W/val
    python -m benchmarks.studies.ablation --train W/train --val W/val --out W/runs --steps 200
    python -m benchmarks.studies.ablation --train W/train --val W/val --out W/runs --rows 2,3,4,5,6 --rendering
    python -m benchmarks.studies.ablation --train W/train --val W/val --out W/runs --recipes paper \
        --variant fp32 --extra "--precision fp32"

The runs are recipes of ``occflownet/train/recipes.py``: ``--rows 1,5`` picks rows of the paper's ablation ladder
(``recipes.ladder()``: 1 ``paper-3d`` … 7 ``paper-2d3d``; 8, 9 add free-space beams), ``--recipes`` names recipes
(default: every ladder row). ``--rendering`` adds the recommended recipe's rendering (``recipes.RENDERING``) to every
run that renders rays and lacks it, recorded as variant ``rendering`` (the ladder with the recommended rendering: row
6 with it is ``recommended``); ``--variant NAME --extra "OPTIONS"`` adds ``occflownet train`` options to every run,
recorded under NAME (an experiment). A run that is its recipe as registered is recorded as variant ``recipe``.

Every run trains ``tiny`` with the same seed and step budget on split ``all`` of the train root (``OUT/VARIANT/
seed<S>/RECIPE``), evaluates the EMA checkpoint on split ``all`` of the val root (mIoU with the camera mask,
RayIoU, static/dynamic mIoU, fog, σ statistics, geometry IoU by τ) and appends a JSON line to ``OUT/results.jsonl``
as it comes. Runs already recorded (variant, recipe, seed, steps) are skipped, so a study resumes, and several
variants and seeds share one OUT. Prints the tables at the end (markdown: per run the scores, geometry and
per-class IoU, fog inside mask_camera, σ over the grid).
"""
from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks.harness import append_jsonl, read_jsonl

RECIPE_VARIANT = "recipe"          # a run that is its recipe as registered
RENDERING_VARIANT = "rendering"    # the recipe with recipes.RENDERING added


@dataclass(frozen=True)
class Run:
    """One configuration of a study: a recipe by name, the variant it is recorded under, and the ``occflownet
    train`` options that train it (``--recipe NAME`` and what the variant adds)."""

    recipe: str
    variant: str
    options: tuple[str, ...]

    @property
    def row(self) -> int | None:
        from occflownet.train.recipes import recipe

        return recipe(self.recipe).ladder_row


def add_run_options(ap: argparse.ArgumentParser, default_recipes: str | None) -> None:
    """``--rows``, ``--recipes``, ``--rendering``, ``--variant``, ``--extra`` (module docstring)."""
    ap.add_argument("--rows", default=None, help="rows of the paper's ablation ladder (recipes.ladder()), e.g. 1,5")
    ap.add_argument("--recipes", default=None,
                    help=f"recipe names (`occflownet recipes`; default: {default_recipes or 'every ladder row'})")
    ap.add_argument("--rendering", action="store_true",
                    help="add the recommended rendering (recipes.RENDERING) to every run that renders rays")
    ap.add_argument("--variant", default=None, help="name the runs are recorded under (needed with --extra)")
    ap.add_argument("--extra", default="", help="extra `occflownet train` options for every run (one string)")


def rendering_options(name: str) -> list[str]:
    """The options that add recipes.RENDERING to recipe ``name`` ([] for a recipe that renders no rays or has it)."""
    from occflownet.choices import supervision_parts
    from occflownet.options import config_argv
    from occflownet.train.recipe import TrainConfig
    from occflownet.train.recipes import RENDERING

    plain = TrainConfig.from_recipe(name)
    if "2d" not in supervision_parts(plain.supervision):
        return []
    return config_argv(TrainConfig.from_recipe(name, **RENDERING), plain)


def selected_runs(ap: argparse.ArgumentParser, args, default_recipes: str | None = None) -> list[Run]:
    """The runs the options of :func:`add_run_options` select (argparse errors for a bad selection)."""
    from occflownet.train.recipes import RECIPES, ladder

    if args.rows and args.recipes:
        ap.error("give --rows or --recipes, not both")
    if args.extra and not args.variant:
        ap.error("--extra needs a --variant name")
    if args.variant in (RECIPE_VARIANT, RENDERING_VARIANT) and args.extra:
        ap.error(f"the variant names {RECIPE_VARIANT!r} and {RENDERING_VARIANT!r} are taken")
    rows = ladder()
    if args.rows:
        try:
            names = [rows[int(r)].name for r in args.rows.split(",")]
        except (KeyError, ValueError):
            ap.error(f"--rows: rows are {', '.join(map(str, sorted(rows)))}")
    else:
        names = (args.recipes or default_recipes or ",".join(r.name for _, r in sorted(rows.items()))).split(",")
    unknown = [n for n in names if n not in RECIPES]
    if unknown:
        ap.error(f"unknown recipe {', '.join(unknown)}; choose among {', '.join(RECIPES)}")
    extra = shlex.split(args.extra)
    runs = []
    for name in names:
        added = rendering_options(name) if args.rendering else []
        variant = args.variant or (RENDERING_VARIANT if added else RECIPE_VARIANT)
        runs.append(Run(name, variant, ("--recipe", name, *added, *extra)))
    return runs


def run_folder(out: Path, run: Run, seed: int) -> Path:
    return out / run.variant / f"seed{seed}" / run.recipe


def record_key(record: dict) -> tuple:
    """(variant, recipe, seed, steps) of a record. Records written before runs were recipes by name carry the
    ladder row and the variant "official" for the rows as they were: the same runs (the ladder's rows were options
    over the paper's settings, the defaults of that time)."""
    from occflownet.train.recipes import ladder

    variant = record.get("variant", RECIPE_VARIANT)
    recipe = record.get("recipe") or ladder()[record["row"]].name
    return (RECIPE_VARIANT if variant == "official" else variant), recipe, record.get("seed", 0), record["steps"]


def train_run(train_root, folder: Path, run: Run, steps: int, seed: int, rays: int, num_workers: int = 1) -> float:
    """Train ``run`` to ``steps`` in ``folder`` (resuming what is there; the learning rate is constant after
    warm-up, so resuming to a larger budget continues the same run) → the seconds this call took."""
    train = [sys.executable, "-m", "occflownet", "train", "--preset", "tiny", "--dataroot", str(train_root),
             "--split", "all", "--out", str(folder), "--max-steps", str(steps), "--rays-per-step", str(rays),
             "--seed", str(seed), "--num-workers", str(num_workers), "--quiet", "--resume", *run.options]
    t0 = time.time()
    print(f"{run.recipe} ({run.variant}), seed {seed}, to {steps} steps\n  {shlex.join(train)}", file=sys.stderr,
          flush=True)
    subprocess.run(train, check=True)
    return time.time() - t0


def evaluate_run(val_root, folder: Path) -> dict:
    """{"metrics": the eval JSON of the run's last checkpoint on split 'all' of ``val_root``, "density": σ figures,
    "geometry_by_tau": geometry IoU inside mask_camera at several τ}."""
    predictions = folder / "val_predictions"
    evaluate = [sys.executable, "-m", "occflownet", "eval", "--checkpoint", str(folder / "checkpoints" / "last.pt"),
                "--dataroot", str(val_root), "--split", "all", "--save-predictions", str(predictions)]
    res = subprocess.run(evaluate, check=True, capture_output=True, text=True)
    out = {"metrics": json.loads(res.stdout), "density": density_stats(predictions),
           "geometry_by_tau": geometry_by_tau(predictions, val_root)}
    shutil.rmtree(predictions)
    return out


def run_record(run: Run, seed: int, steps: int, rays: int, seconds: float) -> dict:
    """The fields of a results line that say which run it is."""
    return {"variant": run.variant, "recipe": run.recipe, "row": run.row, "options": list(run.options),
            "seed": seed, "steps": steps, "rays": rays, "train_seconds": round(seconds, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", required=True)
    ap.add_argument("--val", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--seed", type=int, default=0)
    add_run_options(ap, None)
    ap.add_argument("--num-workers", type=int, default=1)
    ap.add_argument("--phase", choices=["train", "eval", "all"], default="all",
                    help="train only (e.g. several groups of runs in parallel), eval only, or both per run")
    args = ap.parse_args()
    runs = selected_runs(ap, args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / "results.jsonl"
    for run in runs:
        if (run.variant, run.recipe, args.seed, args.steps) in {record_key(r) for r in read_jsonl(results_path)}:
            continue
        folder = run_folder(out, run, args.seed)
        if args.phase in ("train", "all"):
            seconds = train_run(args.train, folder, run, args.steps, args.seed, args.rays, args.num_workers)
            (folder / "train_seconds.txt").write_text(f"{seconds:.1f}")
        if args.phase == "train":
            continue
        seconds = float((folder / "train_seconds.txt").read_text())
        append_jsonl(results_path, {**run_record(run, args.seed, args.steps, args.rays, seconds),
                                    **evaluate_run(args.val, folder)})
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


def _label(record: dict) -> str:
    """"recipe (row R, variant)" of a results line."""
    variant, recipe, _, _ = record_key(record)
    row = record.get("row")
    return f"{recipe}{f' (row {row})' if row else ''}{'' if variant == RECIPE_VARIANT else f', {variant}'}"


def _order(record: dict) -> tuple:
    variant, recipe, seed, steps = record_key(record)
    return record.get("row") or 99, recipe, variant, seed, steps


def table(results_path: Path) -> str:
    """The study's tables (markdown) from its results.jsonl."""
    rows = sorted(read_jsonl(results_path), key=_order)
    lines = ["| run | seed | mIoU (cam mask) | RayIoU | static mIoU | dynamic mIoU | mIoU (no mask) | train s |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m = r["metrics"]
        occ = m["occupancy"]["camera_mask"]
        ray = m.get("rayiou") or {}
        lines.append(f"| {_label(r)} | {r.get('seed', 0)} | {_pct(occ['miou'])} | {_pct(ray.get('rayiou'))} | "
                     f"{_pct(occ['miou_static'])} | {_pct(occ['miou_dynamic'])} | "
                     f"{_pct(m['occupancy']['all_voxels']['miou'])} | {r['train_seconds']:.0f} |")
    shown = ("driveable_surface", "sidewalk", "terrain", "manmade", "car", "truck")
    lines += ["", "| run | seed | geometry IoU | " + " | ".join(shown) + " |", "|---|---|---|" + "---|" * len(shown)]
    for r in rows:
        occ = r["metrics"]["occupancy"]["camera_mask"]
        per_class = occ["iou_per_class"]
        lines.append(f"| {_label(r)} | {r.get('seed', 0)} | {_pct(occ['geometry_iou'])} | "
                     + " | ".join(_pct(per_class.get(name)) for name in shown) + " |")
    return "\n".join(lines + _fog_lines(rows) + _density_lines(rows))


def _fog_lines(rows: list[dict]) -> list[str]:
    lines = ["", "Fog inside mask_camera (eval's `fog`: predicted occupied / labelled occupied voxels; crossed = some "
             "training ray of t ∈ [-3, 3] passes through the voxel):", "",
             "| run | seed | labelled occupied | predicted occupied | fog factor | crossed: factor | never crossed: "
             "factor | never crossed: false positives |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        fog = r["metrics"].get("fog")
        if fog:
            cam, crossed, never = fog["camera_mask"], fog["crossed"], fog["never_crossed"]
            lines.append(f"| {_label(r)} | {r.get('seed', 0)} | {_pct(cam['labelled_fraction'])} % | "
                         f"{_pct(cam['predicted_fraction'])} % | {_ratio(cam['fog_factor'])} | "
                         f"{_ratio(crossed['fog_factor'])} | {_ratio(never['fog_factor'])} | "
                         f"{never['false_positive']} |")
    return lines


def _density_lines(rows: list[dict]) -> list[str]:
    lines = ["", "σ over all voxels of the grid (inside and outside the camera mask):", "",
             "| run | seed | σ median | σ p99 | σ p99.9 | σ max | voxels σ ≥ 0.35 | predicted occupied |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d = r.get("density")
        if d:
            lines.append(f"| {_label(r)} | {r.get('seed', 0)} | {d['median']:.3f} | {d['p99']:.3f} | {d['p999']:.3f} | "
                         f"{d['max']:.3f} | {100 * d['frac_ge_tau']:.2f} % | {100 * d['frac_occupied']:.2f} % |")
    return lines


if __name__ == "__main__":
    sys.exit(main())
