"""Training steps per second, data loading included, of this tree against another commit's, side by side in one run.

    python benchmarks/bench_train_speed.py --dataroot W [--baseline-commit 3fb4338] [--configs 3d,3d-mask,base]
        [--steps 40] [--skip 8] [--rounds 2] [--preset tiny] [--baseline-extra "..."] [--extra "..."]

Each side runs the real ``occflownet train`` of its own tree (the baseline commit checked out in a temporary
``git worktree`` and imported from there, with this interpreter; "today" this checkout), with that tree's
defaults — what a user of each would get — on the prepared root W (split ``all``), for ``--steps`` steps with a
log record every step. Steps/s = (steps − skip) over the wall time between the ``skip``-th and the last log record
(the first steps compile numba kernels, fill caches and start the data workers). The sides alternate for
``--rounds`` rounds (baseline, today, baseline, today, ...) so that both see the same machine load; the table gives
the median per side, the ratio and each side's peak resident memory (the largest over its runs). ``--baseline-extra`` / ``--extra`` add options to one side only (for example
``--precision bf16`` to time today's code under bf16 autocast).

Configurations (``CONFIGS``): ``3d`` (3D labels on every voxel, the official 3D training), ``3d-mask`` (3D labels
inside ``mask_camera``: the quickstart's recipe), ``base`` (the 2D base: rendering, t ∈ [−3, 3], dynamic filter,
disocclusion, loss weighting), ``flow`` (the base with occupancy flow).
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = {
    "3d": ["--supervision", "3d", "--horizon", "0", "--no-flow"],
    "3d-mask": ["--supervision", "3d", "--horizon", "0", "--no-flow", "--voxel-mask"],
    "base": ["--supervision", "2d", "--horizon", "3", "--no-flow"],
    "flow": ["--supervision", "2d", "--horizon", "3", "--flow"],
}


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


def run_side(tree: Path | None, dataroot: str, preset: str, config: str, steps: int, skip: int, extra: list[str],
             workdir: Path) -> tuple[float, float]:
    """One ``occflownet train`` of ``tree`` (None: this checkout) → (steps/s, peak RSS in MB)."""
    out = Path(tempfile.mkdtemp(dir=workdir))
    env = dict(os.environ)
    if tree is not None:  # import the baseline's package first (its occflownet shadows the installed one)
        env["PYTHONPATH"] = os.pathsep.join([str(tree), env.get("PYTHONPATH", "")])
    rss = out / "peak_rss_mb"
    cmd = [sys.executable, "-c", _RUN_AND_MEASURE, str(rss), "train", "--preset", preset, "--dataroot", dataroot,
           "--split", "all",
           "--out", str(out), "--max-steps", str(steps), "--log-every", "1", "--checkpoint-every", str(10 * steps),
           "--quiet", *CONFIGS[config], *extra]
    proc = subprocess.run(cmd, env=env, cwd=workdir, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return steps_per_second(out / "log.jsonl", skip), float(rss.read_text())


def baseline_tree(rev: str, workdir: Path) -> Path:
    tree = workdir / "baseline-tree"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), rev], check=True,
                   capture_output=True)
    return tree


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataroot", required=True)
    p.add_argument("--baseline-commit", default="3fb4338",
                   help="the commit to compare with (default: main before issue 19's work, float32 on CPUs)")
    p.add_argument("--configs", default="3d,3d-mask,base")
    p.add_argument("--preset", default="tiny")
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--skip", type=int, default=8)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--baseline-extra", default="", help="options for the baseline's runs only")
    p.add_argument("--extra", default="", help="options for today's runs only")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_train_speed_") as tmp:
        workdir = Path(tmp)
        tree = baseline_tree(args.baseline_commit, workdir)
        try:
            rows = []
            for config in args.configs.split(","):
                sides = {"baseline": [], "today": []}
                for _ in range(args.rounds):
                    sides["baseline"].append(run_side(tree, args.dataroot, args.preset, config, args.steps, args.skip,
                                                      shlex.split(args.baseline_extra), workdir))
                    sides["today"].append(run_side(None, args.dataroot, args.preset, config, args.steps, args.skip,
                                                   shlex.split(args.extra), workdir))
                (base, base_mb), (today, today_mb) = ((statistics.median(r[0] for r in v), max(r[1] for r in v))
                                                      for v in sides.values())
                rows.append(f"| {args.preset} {config} | {base:.2f} | {today:.2f} | **{today / base:.2f}×** | "
                            f"{base_mb:.0f} / {today_mb:.0f} | "
                            f"{', '.join(f'{v:.2f}' for v, _ in sides['baseline'])} / "
                            f"{', '.join(f'{v:.2f}' for v, _ in sides['today'])} |")
                print(rows[-1], flush=True)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], capture_output=True)
    print(f"\n| config | baseline {args.baseline_commit} steps/s | today steps/s | today ÷ baseline | peak RSS MB "
          f"(baseline / today) | per round (baseline / today) |\n|---|---|---|---|---|---|")
    print("\n".join(rows))
    print(f"(median of {args.rounds} interleaved rounds, steps {args.skip}..{args.steps} of each run, data loading "
          f"included; load average {os.getloadavg()[0]:.1f}; {time.strftime('%Y-%m-%d %H:%M')})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
