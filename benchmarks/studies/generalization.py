"""The generalization benchmark: train `tiny` on K synthetic scenes, score on the scenes of another world seed.

    git archive HEAD occflownet | tar -x -C SNAP     # optional: every run of the study imports the same code
    export OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 PYTHONPATH=SNAP
    python -m benchmarks.studies.generalization --out DIR --check-resume 40      # resumed run == run in one go?
    python -m benchmarks.studies.generalization --out DIR [--variants quickstart,recommended] [--ks 4] \
        [--seeds 0,1,2] [--budgets 300,600,1200]
    python -m benchmarks.studies.generalization --out DIR --table [--ks 4 --variants ...] [--equal-cpu quickstart@1200]

The worlds (made once under ``DIR/worlds``, unless they exist): ``train<N>``, N scenes × F keyframes of world seed
``--train-seed`` (N = the largest K); ``k<K>``, a root that links to ``train<N>``'s files with a ``splits.json``
whose split ``train`` is its first K scenes (so the K's are nested: the 4 scenes of K = 4 are among the 8 of
K = 8), each prepared on its own, so that the class counts (``--loss-weighting``) come from the scenes it trains
on; ``val``, ``--val-scenes`` × F keyframes of world seed ``--val-seed``, scored on split ``all``. F = 8 keyframes
(4 s) per scene, the quickstart's: a temporal ray of O = 3 reaches three keyframes to each side, so a scene much
shorter than 8 keyframes leaves most of its keyframes without a full horizon, and at a fixed cost of about 1.2 s
a keyframe shorter scenes buy more scenes.

Each run trains a *variant* (:func:`variant_overrides`: a base recipe, ``quickstart`` or ``recommended``, plus
levers of :data:`LEVERS`, e.g. ``quickstart+bev-flip+image-aug``) on split ``train`` of ``k<K>`` with one seed,
in ``DIR/runs/<variant>/k<K>/seed<S>``, and is continued through the budgets (the learning rate is constant after
the warm-up, data order and ray draws are functions of (seed, step), so a run resumed to 1,200 steps is the run
trained to 1,200 steps in one go); a variant with a cosine schedule decays over its own max_steps, so it trains
each budget from scratch in ``.../steps<N>``. At each budget the EMA checkpoint is scored on the val world (mIoU
inside mask_camera, per class, static and dynamic, geometry IoU, RayIoU) and on its own training scenes
(train-set mIoU), and one JSON line goes to ``DIR/results.jsonl`` as it comes. Records already there are skipped
(keyed by variant, K, seed, steps), so a stopped study resumes.

Each training chunk runs in a worker process (``--worker``, under ``nice -n 5``) with one torch thread and no
data-loader workers, one at a time; it measures its CPU seconds per step (process CPU time between the ends of its
first and last optimisation steps, divided by the steps between: data loading, step, EMA, logs and checkpoints; not
the set-up), so that variants can be compared at equal CPU time as well as at equal steps (``--table``,
``--equal-cpu``). On a loaded machine the CPU time of the same step varies by about ±10 % (cache and core
sharing), so equal-CPU comparisons need differences larger than that.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from occflownet.train.recipes import IMAGE_SEMANTICS

VERSION = "v1.0-trainval"
FRAMES = 8

# Levers: TrainConfig overrides added to a base recipe, named in a variant as BASE+LEVER[+LEVER...].
LEVERS: dict[str, dict] = {
    "bev-flip": {"bev_flip": True},
    "bev-rotate": {"bev_rotate": True},
    "image-aug": {"image_aug": True},
    "photometric": {"photometric_aug": True},
    "cosine": {"lr_schedule": "cosine"},
    "wd0.05": {"weight_decay": 0.05},
    # rays and free rays a step, one field each; quickstart+rays4096+free2048 is the quickstart recipe's former draw
    # (the K = 2, 4, 8, 16 records in docs/results.md were made with it)
    "rays1024": {"rays_per_step": 1024},
    "rays4096": {"rays_per_step": 4096},
    "rays8192": {"rays_per_step": 8192},
    "free512": {"free_rays_per_step": 512},
    "free2048": {"free_rays_per_step": 2048},
    "ema0.995": {"ema_decay": 0.995},
    "ema0.999": {"ema_decay": 0.999},
    "small": {"preset": "small"},
    "horizon0": {"horizon": 0},
    "no-flow": {"flow": False},
    # the recipes' image term (the LiDAR points' classes on the image features), added or taken away
    "image-sem": dict(IMAGE_SEMANTICS),
    "no-image-sem": {name: 0.0 for name in IMAGE_SEMANTICS},
}


def base_recipes() -> dict[str, dict]:
    """{name: TrainConfig overrides} of the two baselines, read from the recipe registry
    (``occflownet/train/recipes.py``): ``quickstart``, the run ``occflownet quickstart`` trains, and ``recommended``,
    the default of ``occflownet train``."""
    from occflownet.train.recipes import recipe

    return {name: {**recipe(name).settings, "recipe": name} for name in ("quickstart", "recommended")}


def variant_overrides(name: str) -> dict:
    """The TrainConfig overrides of variant ``name`` = BASE[+LEVER...] (ValueError naming the known parts)."""
    base, *levers = name.split("+")
    bases = base_recipes()
    if base not in bases:
        raise ValueError(f"variant {name!r}: unknown base {base!r}; choose one of {sorted(bases)}")
    out = dict(bases[base])
    for lever in levers:
        if lever not in LEVERS:
            raise ValueError(f"variant {name!r}: unknown lever {lever!r}; choose from {sorted(LEVERS)}")
        out.update(LEVERS[lever])
    return out


def continued(overrides: dict) -> bool:
    """Whether one run continued through the budgets equals a run per budget (constant lr after the warm-up)."""
    return overrides.get("lr_schedule", "constant") == "constant"


# --- worlds -----------------------------------------------------------------------------------------------------------

def make_world(root: Path, scenes: int, seed: int) -> None:
    """A prepared synthetic world of ``scenes`` × FRAMES keyframes at ``root`` (kept when it exists)."""
    from occflownet.data.prepare import prepare
    from occflownet.synth.generate import generate

    if not (root / "gts" / "labels.json").is_file():
        generate(root, scenes=scenes, frames=FRAMES, seed=seed, progress=False, overwrite=root.exists())
    if not (root / "occflownet").is_dir():
        prepare(root)


def make_subset(source: Path, root: Path, k: int) -> None:
    """``root``: the files of ``source`` (links) and its tables with split ``train`` = the first ``k`` scenes,
    prepared (the class counts of those scenes)."""
    from occflownet.data.prepare import prepare

    if (root / "occflownet").is_dir():
        return
    root.mkdir(parents=True, exist_ok=True)
    for entry in source.iterdir():
        if entry.name not in (VERSION, "occflownet") and not (root / entry.name).exists():
            (root / entry.name).symlink_to(entry.resolve())
    tables = root / VERSION
    shutil.copytree(source / VERSION, tables, dirs_exist_ok=True)
    scenes = sorted(s["name"] for s in json.loads((tables / "scene.json").read_text()))
    if k > len(scenes):
        raise ValueError(f"{source} has {len(scenes)} scenes, K = {k} asked for")
    (tables / "splits.json").write_text(json.dumps({"train": scenes[:k]}, indent=1))
    prepare(root)


def make_worlds(out: Path, ks: list[int], train_seed: int, val_seed: int, val_scenes: int) -> dict[int, Path]:
    """{K: the root to train on}; the val world at ``out/worlds/val``."""
    worlds = out / "worlds"
    source = worlds / f"train{max(ks)}"
    make_world(worlds / "val", val_scenes, val_seed)
    make_world(source, max(ks), train_seed)
    made = {"train_seed": train_seed, "train_scenes": max(ks), "val_seed": val_seed, "val_scenes": val_scenes,
            "frames": FRAMES}
    stated = worlds / "worlds.json"
    if stated.is_file() and json.loads(stated.read_text()) != made:
        raise SystemExit(f"{worlds} holds the worlds of {stated.read_text()}, not of {made}: use another --out")
    stated.write_text(json.dumps(made))
    roots = {}
    for k in ks:
        roots[k] = worlds / f"k{k}"
        make_subset(source, roots[k], k)
    return roots


# --- the worker: one training chunk and its scores, in a process of its own ------------------------------------------

def _count_steps(loop) -> dict:
    """Wrap ``loop.train_step`` so that each call records the process CPU time at its end; returns the record
    ({"ends": [seconds]}). Without that name in the loop the record stays empty and the chunk's whole CPU time,
    set-up included, stands in."""
    record = {"ends": []}
    step = getattr(loop, "train_step", None)
    if step is None:
        return record

    def timed(*args, **kwargs):
        out = step(*args, **kwargs)
        record["ends"].append(time.process_time())
        return out

    loop.train_step = timed
    return record


def train_chunk(config: dict) -> dict:
    """Train the TrainConfig ``config`` (a dict) to its max_steps, resuming its run; → {"steps", "cpu_s",
    "cpu_s_per_step", "wall_s"}: the steps this call trained, its process CPU seconds, and CPU seconds per step
    between the ends of its first and last steps (None when it trained fewer than 2)."""
    from occflownet.train import loop
    from occflownet.train.recipe import TrainConfig

    ends = _count_steps(loop)["ends"]
    cpu0, wall0 = time.process_time(), time.monotonic()
    loop.train(TrainConfig.from_dict(config), resume=True, progress=False)
    cpu = time.process_time() - cpu0
    per_step = (ends[-1] - ends[0]) / (len(ends) - 1) if len(ends) >= 2 else None
    return {"steps": len(ends), "cpu_s": round(cpu, 2), "cpu_s_per_step": per_step and round(per_step, 4),
            "wall_s": round(time.monotonic() - wall0, 1)}


def score(checkpoint: Path, root: Path, split: str, rayiou: bool) -> dict:
    """The EMA weights of ``checkpoint`` scored on ``split`` of ``root`` (no fog): the camera-mask figures (mIoU,
    static, dynamic, geometry IoU, per class), mIoU on all voxels and the RayIoU figures (when ``rayiou``)."""
    from occflownet.eval.evaluate import evaluate, select_samples
    from occflownet.model import model_from_source
    from occflownet.runtime import TorchPredictor

    result = evaluate(select_samples(root, None, split), TorchPredictor(model_from_source(checkpoint)),
                      rayiou=rayiou, progress=False, fog_horizon=None)
    cam = result["occupancy"]["camera_mask"]
    out = {"samples": result["samples"], "miou": cam["miou"], "miou_static": cam["miou_static"],
           "miou_dynamic": cam["miou_dynamic"], "geometry_iou": cam["geometry_iou"],
           "iou_per_class": cam["iou_per_class"], "miou_all_voxels": result["occupancy"]["all_voxels"]["miou"],
           "eval_s": result["timing"]["seconds"]}
    if rayiou:
        ray = result["rayiou"]
        out["rayiou"] = {k: ray[k] for k in ("rayiou", "rayiou@1", "rayiou@2", "rayiou@4")}
    return out


def checkpoint_step(checkpoint: Path) -> int:
    """The optimiser steps a training checkpoint holds."""
    from occflownet.model.checkpoint import read_checkpoint

    return int(read_checkpoint(checkpoint)["extra"]["train"]["step"])


def worker(job_path: Path) -> int:
    """``--worker JOB.json``: {"config": TrainConfig dict, "val_root", "train_root", "result", "score"}: train the
    chunk, score the checkpoint (unless "score" is false) on the val world and on the training split, write
    {"train", "val", "train_set"} to ``result``."""
    import torch

    torch.set_num_threads(1)
    job = json.loads(job_path.read_text())
    chunk = train_chunk(job["config"])
    checkpoint = Path(job["config"]["out"]) / "checkpoints" / "last.pt"
    chunk["checkpoint_step"] = checkpoint_step(checkpoint)
    if chunk["checkpoint_step"] != job["config"]["max_steps"]:
        raise SystemExit(f"{checkpoint} holds step {chunk['checkpoint_step']}, not the budget "
                         f"{job['config']['max_steps']} (the run went past it earlier): remove the run to score it")
    result = {"train": chunk}
    if job.get("score", True):
        result["val"] = score(checkpoint, Path(job["val_root"]), "all", rayiou=True)
        result["train_set"] = score(checkpoint, Path(job["train_root"]), job["config"]["split"], rayiou=False)
    Path(job["result"]).write_text(json.dumps(result))
    return 0


# --- the study --------------------------------------------------------------------------------------------------------

def records(results: Path) -> list[dict]:
    return [json.loads(line) for line in results.read_text().splitlines() if line.strip()] if results.exists() else []


def key(record: dict) -> tuple:
    return record["variant"], record["k"], record["seed"], record["steps"]


def append(results: Path, record: dict) -> None:
    """Append one JSON line under an exclusive lock (lines stay whole when several studies share the file)."""
    import fcntl

    with open(results, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        f.write(json.dumps(record) + "\n")


def run_config(variant: str, root: Path, run: Path, seed: int, steps: int) -> dict:
    """The resolved TrainConfig (a dict) of one chunk: the variant's overrides, split ``train`` of ``root``, one
    process (no data-loader workers), no time limit."""
    from occflownet.train.recipe import TrainConfig

    cfg = TrainConfig(**{"preset": "tiny", **variant_overrides(variant)}, dataroot=str(root), out=str(run),
                      version=VERSION, split="train", max_steps=steps, seed=seed, num_workers=0, time_limit_s=0.0)
    return cfg.to_dict()


def run_chunk(config: dict, val_root: Path, train_root: Path, scratch: Path, scored: bool = True) -> dict:
    """Train and (when ``scored``) score one chunk in a ``--worker`` process (nice 5, one thread); → the worker's
    result."""
    scratch.mkdir(parents=True, exist_ok=True)
    job, result = scratch / "job.json", scratch / "result.json"
    result.unlink(missing_ok=True)
    job.write_text(json.dumps({"config": config, "val_root": str(val_root), "train_root": str(train_root),
                               "result": str(result), "score": scored}))
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    subprocess.run(["nice", "-n", "5", sys.executable, __file__, "--worker", str(job)], check=True, env=env)
    return json.loads(result.read_text())


def code_tree() -> str:
    """The source tree the runs import occflownet from (a snapshot on PYTHONPATH, or the installed checkout)."""
    import occflownet

    return str(Path(occflownet.__file__).resolve().parents[1])


def run_chain(out: Path, variant: str, k: int, root: Path, seed: int, budgets: list[int], results: Path) -> None:
    """Train ``variant`` on ``root`` (K = ``k``) with ``seed`` through ``budgets``, appending one record per budget
    not yet in ``results``."""
    overrides = variant_overrides(variant)
    chained = continued(overrides)
    folder = out / "runs" / variant / f"k{k}" / f"seed{seed}"
    for steps in budgets:
        if (variant, k, seed, steps) in {key(r) for r in records(results)}:
            continue
        run = folder if chained else folder / f"steps{steps}"
        config = run_config(variant, root, run, seed, steps)
        print(f"[generalization] {variant} K={k} seed {seed} -> {steps} steps ({run})", file=sys.stderr, flush=True)
        t0 = time.time()
        result = run_chunk(config, out / "worlds" / "val", root, run / "job")
        append(results, {"variant": variant, "overrides": overrides, "k": k, "seed": seed, "steps": steps,
                         "continued": chained, "rays_per_step": config["rays_per_step"], "lr": config["lr"],
                         "ema_decay": config["ema_decay"], "preset": config["preset"],
                         "code": code_tree(),
                         "worlds": json.loads((out / "worlds" / "worlds.json").read_text()),
                         **result, "chunk_wall_s": round(time.time() - t0, 1)})


def check_resume(out: Path, variant: str, root: Path, steps: int) -> str:
    """Train ``variant`` on ``root`` for ``steps`` in one go and as two resumed halves (seed 0, logged every step,
    in worker processes); → a line with the largest difference of the logged losses and of the EMA weights."""
    import torch

    logs, weights = [], []
    for name, budgets in (("once", [steps]), ("halves", [steps // 2, steps])):
        run = out / "resume_check" / variant / name
        shutil.rmtree(run, ignore_errors=True)
        for budget in budgets:
            config = run_config(variant, root, run, 0, budget) | {"log_every": 1}
            run_chunk(config, out / "worlds" / "val", root, run / "job", scored=False)
        logs.append({r["step"]: r["loss"] for r in map(json.loads, (run / "log.jsonl").read_text().splitlines())
                     if "loss" in r})
        weights.append(torch.load(run / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)["state_dict"])
    loss_diff = max(abs(logs[0][s] - logs[1][s]) for s in logs[0])
    weight_diff = max(float((weights[0][k].float() - weights[1][k].float()).abs().max()) for k in weights[0])
    return (f"{variant}: {steps} steps in one go against {steps // 2} + {steps - steps // 2} resumed: largest loss "
            f"difference {loss_diff:.3g} over {len(logs[0])} logged steps, largest EMA weight difference "
            f"{weight_diff:.3g}")


# --- tables -----------------------------------------------------------------------------------------------------------

SHOWN_CLASSES = ("car", "truck", "bus", "pedestrian", "driveable_surface", "sidewalk", "terrain", "manmade",
                 "vegetation")


def _val(record: dict, name: str):
    """One figure of a record in % (None when absent): val mIoU etc., ``train_miou``, ``rayiou``, ``class:<c>``."""
    if name == "train_miou":
        value = record["train_set"]["miou"]
    elif name == "rayiou":
        value = record["val"]["rayiou"]["rayiou"]
    elif name.startswith("class:"):
        value = record["val"]["iou_per_class"].get(name[6:])
    else:
        value = record["val"][name]
    return None if value is None else 100 * value


def mean_spread(values: list) -> str:
    """'mean ± sample standard deviation' of the values that are not None (the mean alone for one value)."""
    values = [v for v in values if v is not None]
    if not values:
        return "n/a"
    if len(values) == 1:
        return f"{values[0]:.1f}"
    return f"{statistics.mean(values):.1f} ± {statistics.stdev(values):.1f}"


def _groups(recs: list[dict]) -> dict[tuple, list[dict]]:
    """{(variant, K, steps): its records, one per seed}."""
    groups: dict[tuple, list[dict]] = {}
    for r in recs:
        groups.setdefault((r["variant"], r["k"], r["steps"]), []).append(r)
    return groups


def _cpu_per_step(recs: list[dict]) -> float | None:
    values = [r["train"]["cpu_s_per_step"] for r in recs if r["train"].get("cpu_s_per_step")]
    return statistics.mean(values) if values else None


def curve_table(recs: list[dict]) -> str:
    """Train-vs-val over the budgets: mean ± sd over the seeds of each (variant, K, steps)."""
    lines = ["| variant | K | steps | seeds | val mIoU | train mIoU | train − val | RayIoU | static | dynamic | "
             "geometry | car | CPU s/step |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (variant, k, steps), group in sorted(_groups(recs).items()):
        gap = [_val(r, "train_miou") - _val(r, "miou") for r in group]
        cpu = _cpu_per_step(group)
        figures = [mean_spread([_val(r, name) for r in group])
                   for name in ("miou", "train_miou")] + [mean_spread(gap)] + [
            mean_spread([_val(r, name) for r in group])
            for name in ("rayiou", "miou_static", "miou_dynamic", "geometry_iou", "class:car")]
        lines.append(f"| {variant} | {k} | {steps} | {','.join(str(r['seed']) for r in sorted(group, key=lambda r: r['seed']))} | "
                     + " | ".join(figures) + f" | {'n/a' if cpu is None else f'{cpu:.3f}'} |")
    return "\n".join(lines)


def class_table(recs: list[dict]) -> str:
    """Per-class val IoU (mean ± sd over the seeds) at each (variant, K)'s largest budget."""
    groups = _groups(recs)
    largest = {}
    for variant, k, steps in groups:
        largest[(variant, k)] = max(steps, largest.get((variant, k), 0))
    lines = ["| variant | K | steps | " + " | ".join(SHOWN_CLASSES) + " |", "|---|---|---|" + "---|" * len(SHOWN_CLASSES)]
    for (variant, k), steps in sorted(largest.items()):
        group = groups[(variant, k, steps)]
        lines.append(f"| {variant} | {k} | {steps} | "
                     + " | ".join(mean_spread([_val(r, f"class:{c}") for r in group]) for c in SHOWN_CLASSES) + " |")
    return "\n".join(lines)


def lever_table(recs: list[dict]) -> str:
    """Each variant BASE+LEVERS against BASE at the same K, steps and seed: the differences in val mIoU, car IoU and
    train − val gap, mean ± sd over the paired seeds, and how many of them are positive."""
    by = {key(r): r for r in recs}
    lines = ["| variant | K | steps | seeds | Δ val mIoU | positive | Δ car | Δ dynamic | Δ (train − val) | "
             "CPU s/step ÷ base |", "|---|---|---|---|---|---|---|---|---|---|"]
    for (variant, k, steps), group in sorted(_groups(recs).items()):
        base = variant.split("+")[0]
        pairs = [(r, by[(base, k, r["seed"], steps)]) for r in group
                 if "+" in variant and (base, k, r["seed"], steps) in by]
        if not pairs:
            continue
        diff = {name: [_val(a, name) - _val(b, name) for a, b in pairs
                       if _val(a, name) is not None and _val(b, name) is not None]
                for name in ("miou", "class:car", "miou_dynamic", "train_miou")}
        gap = [x - y for x, y in zip(diff["train_miou"], diff["miou"])]
        cpu, cpu_base = _cpu_per_step([a for a, _ in pairs]), _cpu_per_step([b for _, b in pairs])
        ratio = f"{cpu / cpu_base:.2f}" if cpu and cpu_base else "n/a"
        lines.append(f"| {variant} | {k} | {steps} | {','.join(str(a['seed']) for a, _ in pairs)} | "
                     f"{mean_spread(diff['miou'])} | {sum(d > 0 for d in diff['miou'])}/{len(diff['miou'])} | "
                     f"{mean_spread(diff['class:car'])} | {mean_spread(diff['miou_dynamic'])} | {mean_spread(gap)} | "
                     f"{ratio} |")
    return "\n".join(lines)


def _at_cpu(chain: list[dict], seconds: float):
    """Val mIoU (%) of one seed's chain at ``seconds`` of training CPU time, linear between its budgets (CPU time
    at a budget = steps × the chain's mean CPU seconds per step); None outside them."""
    per_step = _cpu_per_step(chain)
    if per_step is None:
        return None
    points = sorted((r["steps"] * per_step, _val(r, "miou")) for r in chain)
    for (c0, v0), (c1, v1) in zip(points, points[1:]):
        if c0 <= seconds <= c1:
            return v0 + (v1 - v0) * (seconds - c0) / (c1 - c0)
    return points[0][1] if math.isclose(points[0][0], seconds, rel_tol=1e-3) else None


def equal_cpu_table(recs: list[dict], reference: str) -> str:
    """Val mIoU at the CPU time of ``reference`` = VARIANT@STEPS (its mean CPU s/step × STEPS, per K), each variant
    interpolated along its budgets (only the continued runs, whose budgets lie on one run)."""
    ref_variant, ref_steps = reference.rsplit("@", 1)
    lines = [f"Val mIoU at the training CPU time of {ref_variant} at {ref_steps} steps:", "",
             "| variant | K | CPU s | steps there | seeds | val mIoU |", "|---|---|---|---|---|---|"]
    chains: dict[tuple, list[dict]] = {}
    for r in recs:
        if r.get("continued", True):
            chains.setdefault((r["variant"], r["k"]), []).append(r)
    for (variant, k), chain in sorted(chains.items()):
        ref = [r for r in chains.get((ref_variant, k), [])]
        ref_cpu = _cpu_per_step(ref)
        per_step = _cpu_per_step(chain)
        if ref_cpu is None or per_step is None:
            continue
        seconds = ref_cpu * int(ref_steps)
        seeds = sorted({r["seed"] for r in chain})
        values = [_at_cpu([r for r in chain if r["seed"] == s], seconds) for s in seeds]
        lines.append(f"| {variant} | {k} | {seconds:.0f} | {seconds / per_step:.0f} | "
                     f"{','.join(str(s) for s, v in zip(seeds, values) if v is not None)} | {mean_spread(values)} |")
    return "\n".join(lines)


def tables(results: Path, variants: list[str] | None, ks: list[int] | None, equal_cpu: list[str]) -> str:
    recs = [r for r in records(results) if (not variants or r["variant"] in variants) and (not ks or r["k"] in ks)]
    parts = ["Val world (split all) against the training scenes, mean ± sd over the seeds, values in %:", "",
             curve_table(recs), "", "Per class on the val world, at the largest budget:", "", class_table(recs), "",
             "Levers against their base, paired by seed (points):", "", lever_table(recs)]
    for reference in equal_cpu:
        parts += ["", equal_cpu_table(recs, reference)]
    return "\n".join(parts)


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="the study's folder: worlds/, runs/, results.jsonl")
    ap.add_argument("--variants", default="", help="comma-separated BASE[+LEVER...] (bases: quickstart, recommended; "
                                                   f"levers: {', '.join(LEVERS)}); default quickstart (--table: all)")
    ap.add_argument("--ks", default="", help="training scenes K, comma-separated (nested subsets of one world); "
                                             "default 4 (--table: all)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--budgets", default="300,600,1200", help="steps at which each run is scored")
    ap.add_argument("--world-ks", default="2,4,8,16", help="the K roots to make (the train world has the largest)")
    ap.add_argument("--train-seed", type=int, default=47)
    ap.add_argument("--val-seed", type=int, default=1047)
    ap.add_argument("--val-scenes", type=int, default=4)
    ap.add_argument("--table", action="store_true", help="print the tables of results.jsonl and stop")
    ap.add_argument("--equal-cpu", default="", help="with --table: VARIANT@STEPS references (comma-separated) for "
                                                    "the equal-CPU-time table")
    ap.add_argument("--check-resume", type=int, default=0, metavar="STEPS",
                    help="train each variant on the first K for STEPS in one go and in two resumed halves, compare, "
                         "stop")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        return worker(Path(args.worker))
    if not args.out:
        ap.error("--out is required")
    out = Path(args.out)
    results = out / "results.jsonl"
    variants, ks = [v for v in args.variants.split(",") if v], _ints(args.ks)
    if args.table:
        print(tables(results, variants, ks, [e for e in args.equal_cpu.split(",") if e]))
        return 0
    variants, ks = variants or ["quickstart"], ks or [4]
    for variant in variants:
        variant_overrides(variant)                       # fail on a bad name before any work
    roots = make_worlds(out, sorted(set(_ints(args.world_ks)) | set(ks)), args.train_seed, args.val_seed,
                        args.val_scenes)
    if args.check_resume:
        for variant in variants:
            print(check_resume(out, variant, roots[ks[0]], args.check_resume))
        return 0
    for variant in variants:
        for k in ks:
            for seed in _ints(args.seeds):
                run_chain(out, variant, k, roots[k], seed, sorted(_ints(args.budgets)), results)
    print(tables(results, variants, ks, []))
    return 0


if __name__ == "__main__":
    sys.exit(main())
