"""`occflownet prepare`: build the sample index (and class counts, flow)."""
from ._pending import not_yet

HELP = "build the sample index (and class counts, flow)"


def add_arguments(parser):
    pass


def run(args) -> int:
    return not_yet("prepare", 2)
