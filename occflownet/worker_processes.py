"""Started ("spawn") worker processes, and the check that makes them safe to start from a user's script.

Every pool of worker processes in this package (the training loader's workers, the labels pipeline, the flow
records) is started with the ``spawn`` context: a fork of a process whose OpenMP runtime already ran parallel
regions can wait forever in the child (see ``train/loop.py``).

A started worker imports the parent's main script again before it runs anything. If that script calls
``train()``, ``run_quickstart()`` or a pool at module level, outside ``if __name__ == "__main__":``, the worker
runs the script's work again and dies while bootstrapping, and the parent, still writing the worker's payload
into a pipe whose read end it holds (CPython's ``popen_spawn_posix``), waits forever with no message.
:func:`spawn_context` refuses that case before any worker starts, with an error that names the script and line.
"""
from __future__ import annotations

import ast
import multiprocessing
import sys
from pathlib import Path


class UnguardedMainError(RuntimeError):
    """Worker processes were asked for from a main script's module level, outside its ``__main__`` guard."""


def spawn_context() -> multiprocessing.context.SpawnContext:
    """The ``spawn`` multiprocessing context, once :func:`check_main_guarded` has passed."""
    check_main_guarded()
    return multiprocessing.get_context("spawn")


def check_main_guarded() -> None:
    """Raise :class:`UnguardedMainError` when this call comes from the main script's module level, outside a
    top-level ``if __name__ == "__main__":`` block (a started worker would run that line again).

    Calls from the command line (``occflownet``, ``python -m occflownet``: a package's ``__main__`` is not run
    again), from an interactive session, from ``python -c`` and from inside a guarded block (directly or through
    functions it calls) pass; so does everything when the main script's source is unreadable.
    """
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if path is None or not Path(path).is_file() or not _spawn_runs_main_again(main, path):
        return
    line = _main_module_line(main)
    if line is None:
        return
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError):
        return
    if not any(_is_main_guard(node) and node.lineno <= line <= node.end_lineno for node in tree.body):
        raise UnguardedMainError(
            f"{path}, line {line}: worker processes are started (spawn) from this script's module level. Each "
            f"worker imports the script again and would run this line too, so the run would hang. Put the call "
            f'under `if __name__ == "__main__":` (https://docs.python.org/3/library/multiprocessing.html'
            f"#the-spawn-and-forkserver-start-methods), or ask for no worker processes (train: --num-workers 0).")


def _spawn_runs_main_again(main, path: str) -> bool:
    """Whether a started worker runs the main module's code again, as CPython's ``multiprocessing.spawn`` decides:
    not for a package's ``__main__`` (``python -m occflownet``, a directory, a zip) nor for ``ipython``; yes for a
    script run by path and for any other module run with ``-m``."""
    name = getattr(getattr(main, "__spec__", None), "name", None)
    if name is not None:
        return not (name == "__main__" or name.endswith(".__main__"))
    return Path(path).stem != "ipython"


def _main_module_line(main) -> int | None:
    """The line of the main script's module-level code that this call comes from, or ``None`` when the call does
    not come from its module level (e.g. an interactive session, or the script already finished importing)."""
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_code.co_name == "<module>" and frame.f_globals is vars(main):
            return frame.f_lineno
        frame = frame.f_back
    return None


def _is_main_guard(node: ast.stmt) -> bool:
    """Whether a top-level statement is ``if __name__ == "__main__":`` (either operand order)."""
    if not (isinstance(node, ast.If) and isinstance(node.test, ast.Compare) and len(node.test.ops) == 1
            and isinstance(node.test.ops[0], ast.Eq)):
        return False
    operands = [node.test.left, *node.test.comparators]
    names = [o for o in operands if isinstance(o, ast.Name) and o.id == "__name__"]
    consts = [o for o in operands if isinstance(o, ast.Constant) and o.value == "__main__"]
    return len(names) == 1 and len(consts) == 1
