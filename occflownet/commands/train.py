"""`occflownet train`: train a model."""
from ._pending import not_yet

HELP = "train a model"


def add_arguments(parser):
    pass


def run(args) -> int:
    return not_yet("train", 6)
