"""One module per command-line verb. Each defines ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``.

Command modules import at module level only the standard library and the configuration dataclasses their options
are derived from (``occflownet/options.py``; modules that import no torch, scipy or numba), so ``occflownet --help``
(and the torch-free ``serve`` and ``predict --model`` paths) stay light; the work is imported inside ``run``.
"""
