"""Training steps per second, data loading included, of this checkout against a baseline commit's, interleaved in one
run, per recipe.

    python -m benchmarks.perf.bench_train_speed --dataroot W [--baseline-commit REV] [--recipes recommended,quickstart]
        [--steps 40] [--skip 8] [--rounds 2] [--preset tiny] [--baseline-extra "..."] [--extra "..."] [--jsonl PATH]

Each side runs the real ``occflownet train`` of its own tree (the baseline commit, default ``HEAD``, checked out in
a temporary ``git worktree`` and imported from there with this interpreter; "today" this checkout, uncommitted
changes included) on the prepared root W (split ``all``) for ``--steps`` steps with a log record every step, the
rest of each tree's defaults. A recipe of today's registry (``occflownet/train/recipes.py``) is given to each tree
as ``benchmarks.harness.recipe_argv`` spells it: ``--recipe NAME`` where that tree's registry has the name, else
the recipe's settings as options over the paper's settings (the defaults of a tree older than the registry); a
baseline without an option for one of them fails, and gets its options from ``--baseline-extra``.
``--baseline-extra`` / ``--extra`` add options to one side only (e.g. ``--precision bf16`` on today's side).

Steps/s = (steps − skip) over the wall time between the ``skip``-th and the last log record (the first steps
compile numba kernels, fill caches and start the data workers). The sides alternate for ``--rounds`` rounds
(``benchmarks.harness.interleaved``: baseline, today, today, baseline, ...). Prints per recipe a table row (median
steps/s per side, today ÷ baseline, each side's peak resident memory, the rounds) with the load average and the
float32 matmul rate, and appends it to ``--jsonl``.
"""
from __future__ import annotations

import argparse
import json
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.harness import Results, add_jsonl_option, interleaved, recipe_argv, tree_env, worktree

# Runs `occflownet train` in this interpreter and writes the process's peak RSS (MB) to the file named first.
_RUN_AND_MEASURE = """
import resource, sys
from occflownet.cli import main
status = main(sys.argv[2:])
with open(sys.argv[1], "w") as f:
    f.write(str(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))
sys.exit(status)
"""


def steps_per_second(log: Path, skip: int) -> float:
    """(steps − skip) / seconds between the log records of step ``skip`` and of the last step."""
    records = [json.loads(line) for line in log.read_text().splitlines()]
    first = next(r for r in records if r["step"] == skip)
    last = records[-1]
    return (last["step"] - first["step"]) / (last["time"] - first["time"])


def run_side(tree: Path | None, options: list[str], args, workdir: Path) -> tuple[float, float]:
    """One ``occflownet train`` of ``tree`` (None: this checkout) with ``options`` → (steps/s, peak RSS in MB)."""
    out = Path(tempfile.mkdtemp(dir=workdir))
    rss = out / "peak_rss_mb"
    cmd = [sys.executable, "-c", _RUN_AND_MEASURE, str(rss), "train", "--preset", args.preset, "--dataroot",
           args.dataroot, "--split", "all", "--out", str(out), "--max-steps", str(args.steps), "--log-every", "1",
           "--checkpoint-every", str(10 * args.steps), "--quiet", *options]
    proc = subprocess.run(cmd, env=tree_env(tree), cwd=workdir, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{shlex.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return steps_per_second(out / "log.jsonl", args.skip), float(rss.read_text())


def compare(name: str, tree: Path, args, workdir: Path, results: Results) -> None:
    """The interleaved rounds of recipe ``name`` on both sides, recorded as one result."""
    options = {"baseline": recipe_argv(name, tree) + shlex.split(args.baseline_extra),
               "today": recipe_argv(name) + shlex.split(args.extra)}
    runs = interleaved({side: (lambda side=side: run_side(tree if side == "baseline" else None, options[side],
                                                           args, workdir)) for side in ("baseline", "today")},
                       args.rounds)
    rates = {side: [value[0] for _, value in v] for side, v in runs.items()}
    peak = {side: max(value[1] for _, value in v) for side, v in runs.items()}
    base, today = (statistics.median(rates[s]) for s in ("baseline", "today"))
    line = (f"| {args.preset} {name} | {base:.2f} | {today:.2f} | **{today / base:.2f}×** | "
            f"{peak['baseline']:.0f} / {peak['today']:.0f} | "
            f"{', '.join(f'{v:.2f}' for v in rates['baseline'])} / {', '.join(f'{v:.2f}' for v in rates['today'])} |")
    results.add({"recipe": name, "preset": args.preset, "baseline_commit": args.baseline_commit,
                 "steps_per_s": {"baseline": base, "today": today}, "rounds": rates, "peak_rss_mb": peak,
                 "options": options, "steps": args.steps, "skip": args.skip}, line)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataroot", required=True)
    p.add_argument("--baseline-commit", default="HEAD", help="the commit to compare with (default: HEAD, so that "
                                                             "today's side measures the uncommitted changes)")
    p.add_argument("--recipes", default="recommended,quickstart", help="recipe names (`occflownet recipes`)")
    p.add_argument("--preset", default="tiny")
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--skip", type=int, default=8)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--baseline-extra", default="", help="options for the baseline's runs only")
    p.add_argument("--extra", default="", help="options for today's runs only")
    add_jsonl_option(p)
    args = p.parse_args(argv)
    results = Results("bench_train_speed", args.jsonl)
    print(f"| recipe | baseline {args.baseline_commit} steps/s | today steps/s | today ÷ baseline | peak RSS MB "
          f"(baseline / today) | per round (baseline / today) | machine |\n|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="bench_train_speed_") as tmp, worktree(args.baseline_commit) as tree:
        for name in args.recipes.split(","):
            compare(name, tree, args, Path(tmp), results)
    print(f"(median of {args.rounds} interleaved rounds, steps {args.skip}..{args.steps} of each run, data loading "
          f"included)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
