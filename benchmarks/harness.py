"""The benchmarks' shared harness: how a benchmark runs two sides, what it prints beside each figure, and where its
results go. Scripts run from the repository root as modules (``python -m benchmarks.perf.NAME``,
``python -m benchmarks.studies.NAME``).

- :func:`machine_state`: the 1-minute load average and this machine's float32 matmul rate (1024³ products,
  ``occflownet.quickstart.matmul_gflops``, with ``threads`` torch threads): printed and recorded with every result,
  so that a figure is read against the state of the (often shared) machine it ran on.
- :class:`Results`: each result printed with the machine's state and appended, as it comes, as one JSON line to a
  file (:func:`append_jsonl`: one line per record, flushed, under an exclusive lock so several processes can share a
  file); a benchmark's ``--jsonl PATH`` (:func:`add_jsonl_option`).
- :func:`interleaved`: two or more sides run in turn, round after round, the order reversed every other round
  (A B, B A, A B, ...), so that the machine's load hits every side alike.
- :func:`worktree` and :func:`tree_env`: a baseline commit checked out in a temporary ``git worktree``, and the
  environment in which a child process imports that tree's ``occflownet`` (or this checkout's).
- :func:`recipe_argv`: the ``occflownet train`` options that train a recipe of today's registry
  (``occflownet/train/recipes.py``) with a given tree's code, the tree being older than the registry or not.
- :func:`module_argv`: the command that runs a benchmark module in a child process.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"          # the real data of the development machine (read-only)
T = TypeVar("T")


def matmul_gflops(threads: int | None = None, seconds: float = 0.5) -> float | None:
    """This machine's float32 matmul rate (GFLOP/s, 1024³ products for about ``seconds``) with ``threads`` torch
    threads (None: torch's current number); None where torch is not installed."""
    try:
        import torch
    except ImportError:
        return None
    from occflownet.quickstart import matmul_gflops as measure

    before = torch.get_num_threads()
    torch.set_num_threads(threads or before)
    try:
        return measure(seconds=seconds)
    finally:
        torch.set_num_threads(before)


def machine_state(threads: int | None = None, seconds: float = 0.5) -> dict:
    """{"load_average": the 1-minute load average, "matmul_gflops": :func:`matmul_gflops`, "matmul_threads"}."""
    try:
        import torch

        threads = threads or torch.get_num_threads()
    except ImportError:
        threads = None
    return {"load_average": round(os.getloadavg()[0], 2), "matmul_gflops": _round(matmul_gflops(threads, seconds)),
            "matmul_threads": threads}


def state_text(state: Mapping) -> str:
    """One line of :func:`machine_state`: "load 1.23, matmul 345 GFLOP/s (2 threads)"."""
    rate = state.get("matmul_gflops")
    matmul = "n/a" if rate is None else f"{rate:.0f} GFLOP/s ({state.get('matmul_threads')} threads)"
    return f"load {state['load_average']:.2f}, float32 matmul {matmul}"


def _round(x: float | None) -> float | None:
    return None if x is None else round(x, 1)


def append_jsonl(path: str | Path, record: Mapping) -> None:
    """Append ``record`` as one JSON line to ``path`` and flush it; an exclusive lock keeps lines whole when several
    processes share the file."""
    import fcntl

    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        f.write(json.dumps(record) + "\n")
        f.flush()


def read_jsonl(path: str | Path) -> list[dict]:
    """The records of a JSON-lines file ([] when it does not exist)."""
    path = Path(path)
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.exists() else []


def add_jsonl_option(parser) -> None:
    """``--jsonl PATH``: where :class:`Results` appends each result as it comes."""
    parser.add_argument("--jsonl", default=None, metavar="PATH",
                        help="append each result as one JSON line to PATH as it comes (with the load average and "
                             "the float32 matmul rate)")


class Results:
    """The results of one benchmark run: :meth:`add` prints a result with the machine's state and appends it to
    ``path`` (when given) as a JSON line {"benchmark", "time", fields of the result, fields of the state}."""

    def __init__(self, benchmark: str, path: str | Path | None = None, *, threads: int | None = None,
                 matmul_seconds: float = 0.5):
        self.benchmark, self.path = benchmark, Path(path) if path else None
        self.threads, self.matmul_seconds = threads, matmul_seconds
        if self.path:
            self.path.parent.mkdir(parents=True, exist_ok=True)

    def state(self) -> dict:
        return machine_state(self.threads, self.matmul_seconds)

    def add(self, record: Mapping, line: str | None = None, state: Mapping | None = None) -> dict:
        """Print ``line`` (default: the record as JSON) followed by the machine's state (``state``, or measured
        now; a line that is a markdown table row, ending in "|", gets it as one more cell), and append the whole
        record → the record as written."""
        state = dict(state) if state is not None else self.state()
        full = {"benchmark": self.benchmark, "time": time.strftime("%Y-%m-%dT%H:%M:%S"), **record, **state}
        line = line if line is not None else json.dumps(dict(record))
        print(f"{line} {state_text(state)} |" if line.rstrip().endswith("|") else f"{line}  [{state_text(state)}]",
              flush=True)
        if self.path:
            append_jsonl(self.path, full)
        return full

    def note(self, line: str) -> dict:
        """Print a header line with the machine's state (no record)."""
        state = self.state()
        print(f"{line}  [{state_text(state)}]", flush=True)
        return state


def interleaved(sides: Mapping[str, Callable[[], T]], rounds: int, *,
                alternate: bool = True) -> dict[str, list[tuple[float, T]]]:
    """Run every side once a round for ``rounds`` rounds, in the order given and, with ``alternate``, reversed every
    other round (A B, B A, A B, ...), so that the machine's load hits all sides alike → {side: [(wall seconds,
    what the side returned) per round]}."""
    out: dict[str, list[tuple[float, T]]] = {name: [] for name in sides}
    names = list(sides)
    for r in range(rounds):
        for name in (names[::-1] if alternate and r % 2 else names):
            t0 = time.perf_counter()
            value = sides[name]()
            out[name].append((time.perf_counter() - t0, value))
    return out


@contextmanager
def worktree(rev: str) -> Iterator[Path]:
    """Commit ``rev`` checked out (detached) in a temporary ``git worktree`` of this repository, removed after."""
    folder = Path(tempfile.mkdtemp(prefix="occflownet-baseline-"))
    tree = folder / "tree"
    proc = subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(tree), rev],
                          capture_output=True, text=True)
    if proc.returncode:
        shutil.rmtree(folder, ignore_errors=True)
        raise SystemExit(f"git worktree add {rev} failed: {proc.stderr.strip()}")
    try:
        yield tree
    finally:
        subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)


def tree_env(tree: Path | None = None, **variables: str) -> dict[str, str]:
    """The environment of a child process that imports ``tree``'s ``occflownet`` (None: this checkout) and finds
    the ``benchmarks`` package, with ``variables`` set (e.g. ``OMP_NUM_THREADS="2"``)."""
    env = dict(os.environ) | variables
    first = [str(tree)] if tree is not None else []
    env["PYTHONPATH"] = os.pathsep.join([*first, str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    return env


def module_argv(module: str) -> list[str]:
    """The command that runs benchmark module ``module`` (``__spec__.name``) in a child process (with
    :func:`tree_env`'s environment or the repository root as working folder)."""
    return [sys.executable, "-m", module]


def tree_recipes(tree: Path | None) -> tuple[str, ...]:
    """The recipe names of ``tree``'s registry; () for a tree older than the registry."""
    if tree is None:
        from occflownet.train.recipes import RECIPE_NAMES

        return RECIPE_NAMES
    proc = subprocess.run([sys.executable, "-c", "from occflownet.train.recipes import RECIPE_NAMES as n; "
                           "print(','.join(n))"], env=tree_env(tree), cwd=tree, capture_output=True, text=True)
    return tuple(proc.stdout.strip().split(",")) if proc.returncode == 0 else ()


def recipe_argv(name: str, tree: Path | None = None) -> list[str]:
    """The ``occflownet train`` options that train recipe ``name`` of today's registry with the code of ``tree``
    (None: this checkout): ``--recipe NAME`` where that tree's registry has the name; otherwise the recipe's
    settings spelled as options (``occflownet.options.config_argv``) over the paper's settings, which are
    ``TrainConfig()``'s defaults and the defaults of a tree older than the registry (a tree with a registry but
    without the name gets ``--recipe paper`` first). A tree that has no option for one of those settings fails in
    its own ``occflownet train``: give such a baseline its options by hand (``--baseline-extra``)."""
    from occflownet.options import config_argv
    from occflownet.train.recipe import TrainConfig

    known = tree_recipes(tree)
    if name in known:
        return ["--recipe", name]
    settings = config_argv(TrainConfig.from_recipe(name), TrainConfig(recipe=name))
    return (["--recipe", "paper"] if known else []) + settings
