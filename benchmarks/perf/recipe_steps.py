"""The seconds of one ``tiny`` training step per recipe, on this machine and scaled to the reference machine: the
figures ``Recipe.step_seconds`` of ``occflownet/train/recipes.py`` holds (and ``occflownet recipes`` lists).

    python -m benchmarks.perf.recipe_steps [--recipes recommended,quickstart,...] [--steps 24] [--skip 8]
        [--rounds 1] [--world W] [--jsonl PATH]

The world is the quickstart's (``occflownet synth`` with QuickstartConfig's scenes, frames and seed, then
``occflownet prepare``; made in ``--world`` when it holds none, by default in a temporary folder). Each recipe
(default: all of them) runs the real ``occflownet train --recipe NAME --preset tiny`` on the world's split ``train``
(the quickstart's) for ``--steps`` steps on the CPU (``--device cpu``): float32 (``--precision fp32``), 2 torch and
numba threads (``OMP_NUM_THREADS``, ``NUMBA_NUM_THREADS``), the data workers ``occflownet train`` defaults to, a log
record every step. A step's seconds are the median of the intervals between consecutive log records after the first
``--skip`` steps (which compile numba kernels, start the workers and fill their caches: several times slower); with
``--rounds`` > 1 the recipes run in turn round after round, the order reversed every other round
(``benchmarks.harness.interleaved``), and the median over the rounds is taken.

Prints a markdown table, one row per recipe as it finishes: seconds per step here, this machine's float32 matmul
rate (1024³, 2 threads) measured right after it, the same seconds scaled to the reference machine
(here × GFLOP/s here ÷ ``recipes.REFERENCE_GFLOPS``: the value for ``step_seconds``), the registered value, and the
load average; each row also as a JSON line to ``--jsonl``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.harness import Results, add_jsonl_option, interleaved, tree_env

THREADS = 2


def make_world(world: Path) -> None:
    """The quickstart's world (its scenes, frames and seed) in ``world``, prepared; kept when it is there."""
    from occflownet.quickstart import QuickstartConfig, synth_argv, synth_settings

    if not (world / "gts" / "labels.json").is_file():
        settings = synth_settings(QuickstartConfig(), preview=False, overwrite=True)
        subprocess.run([sys.executable, "-m", "occflownet", *synth_argv(world, settings), "--no-progress"], check=True)
    if not (world / "occflownet").is_dir():
        subprocess.run([sys.executable, "-m", "occflownet", "prepare", "--dataroot", str(world), "--quiet"], check=True)


def step_seconds(log: Path, skip: int) -> float:
    """Median seconds between consecutive log records after step ``skip``."""
    times = [r["time"] for r in map(json.loads, log.read_text().splitlines()) if r["step"] >= skip]
    if len(times) < 2:
        raise SystemExit(f"{log}: fewer than two steps after the first {skip}; give more --steps")
    return statistics.median(b - a for a, b in zip(times, times[1:]))


def run_recipe(name: str, world: Path, args, workdir: Path) -> float:
    """One ``occflownet train`` of recipe ``name`` → its seconds per step."""
    out = Path(tempfile.mkdtemp(dir=workdir, prefix=f"{name}-"))
    cmd = [sys.executable, "-m", "occflownet", "train", "--recipe", name, "--preset", "tiny", "--dataroot",
           str(world), "--split", "train", "--out", str(out), "--max-steps", str(args.steps), "--log-every", "1",
           "--checkpoint-every", str(10 * args.steps), "--device", "cpu", "--precision", "fp32", "--quiet"]
    proc = subprocess.run(cmd, env=tree_env(OMP_NUM_THREADS=str(THREADS), NUMBA_NUM_THREADS=str(THREADS)),
                          capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return step_seconds(out / "log.jsonl", args.skip)


def record(results: Results, name: str, here: float, extra: dict) -> None:
    """One table row and JSON line: recipe ``name`` at ``here`` seconds a step, scaled by the matmul rate now."""
    from occflownet.train.recipes import REFERENCE_GFLOPS, recipe

    state = results.state()
    scaled = here * state["matmul_gflops"] / REFERENCE_GFLOPS
    registered = recipe(name).step_seconds
    results.add({"recipe": name, "step_seconds_here": round(here, 4), "step_seconds_reference": round(scaled, 3),
                 "reference_gflops": REFERENCE_GFLOPS, **extra},
                f"| {name} | {here:.3f} | {state['matmul_gflops']:.0f} | **{scaled:.3f}** | "
                f"{'—' if registered is None else f'{registered:.3f}'} |", state)


TABLE_HEAD = ("| recipe | s/step here | float32 matmul here (GFLOP/s) | s/step on the reference | registered | "
              "machine |\n|---|---|---|---|---|---|")


def main(argv=None) -> int:
    from occflownet.train.recipes import RECIPE_NAMES, REFERENCE_GFLOPS, recipe

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--recipes", default=",".join(RECIPE_NAMES), help="recipe names (default: every recipe)")
    p.add_argument("--steps", type=int, default=24)
    p.add_argument("--skip", type=int, default=8, help="first steps left out (compilation, workers, caches)")
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--world", default=None, help="the quickstart's world, prepared (made there when missing; "
                                                 "default: a temporary folder)")
    add_jsonl_option(p)
    args = p.parse_args(argv)
    names = args.recipes.split(",")
    for name in names:
        recipe(name)                                          # an unknown name fails before any work
    results = Results("recipe_steps", args.jsonl, threads=THREADS, matmul_seconds=2.0)
    with tempfile.TemporaryDirectory(prefix="recipe_steps_") as tmp:
        world = Path(args.world) if args.world else Path(tmp) / "world"
        make_world(world)
        print(f"tiny, float32, {THREADS} threads, steps {args.skip}..{args.steps} (median); reference machine "
              f"{REFERENCE_GFLOPS:g} GFLOP/s; one row per run, as it finishes\n\n{TABLE_HEAD}", flush=True)
        settings = {"steps": args.steps, "skip": args.skip}

        def side(name: str) -> float:
            here = run_recipe(name, world, args, Path(tmp))
            record(results, name, here, settings)
            return here

        runs = interleaved({name: (lambda name=name: side(name)) for name in names}, args.rounds)
    if args.rounds > 1:
        print(f"\nmedian of {args.rounds} rounds per recipe:\n\n{TABLE_HEAD}")
        for name, values in runs.items():
            record(results, name, statistics.median(v for _, v in values),
                   {**settings, "rounds": [round(v, 4) for _, v in values]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
