"""`occflownet quickstart`: synthetic world -> train -> eval -> export."""
from ._pending import not_yet

HELP = "synthetic world -> train -> eval -> export"


def add_arguments(parser):
    pass


def run(args) -> int:
    return not_yet("quickstart", 6)
