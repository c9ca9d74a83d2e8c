"""`occflownet synth`: synthetic nuScenes-format world."""
from ._pending import not_yet

HELP = "synthetic nuScenes-format world"


def add_arguments(parser):
    pass


def run(args) -> int:
    return not_yet("synth", 2)
