"""One module per command-line verb. Each defines ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``.

Command modules import only the standard library at module level, so ``occflownet --help`` (and the torch-free
``serve`` and ``predict --model`` paths) stay light; the work is imported inside ``run``.
"""
