"""`occflownet predict`: predict occupancy for one set of six images."""
from ._pending import not_yet

HELP = "predict occupancy for one set of six images"


def add_arguments(parser):
    pass


def run(args) -> int:
    return not_yet("predict", 3)
